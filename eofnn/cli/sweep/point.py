"""One point of a sweep on disk: run it as ``eofnn compare`` in its folder, mark it done or failed, read it back.

A point's folder holds ``point.yaml`` (its full resolved config), ``log.txt`` (compare's messages), ``run/``
(compare's output folder: ``metrics.json``, ``results.md``, ``config.yaml``, figures, checkpoints; compare moves it
into place only when complete) and, written atomically once compare has returned, ``status.json``:
``{"status": "done" | "failed", "error": ..., "seconds": ...}``. A point is finished only when ``status.json``
says done; anything else is rerun from scratch.
"""

from __future__ import annotations

import contextlib
import json
import shutil
import signal
import threading
import time
import traceback
from pathlib import Path

from threadpoolctl import threadpool_limits

from eofnn.outputs import write_text_atomic

STATUS_FILE = "status.json"
CONFIG_FILE = "point.yaml"
LOG_FILE = "log.txt"
RUN_DIR = "run"
#: Exit status of an interrupted command (128 + SIGINT), as a shell reports Ctrl-C.
INTERRUPTED = 130
ERROR_PREFIX = "eofnn: error: "


def write_atomic(path: Path, text: str) -> bool:
    """Write ``text`` to ``path`` atomically (:func:`eofnn.outputs.write_text_atomic`), unless the file already holds
    it: then it is left alone (not rewritten, its time stamp kept). Returns whether it was written."""
    try:
        if path.is_file() and path.read_text() == text:
            return False
    except (OSError, UnicodeDecodeError):
        pass
    write_text_atomic(path, text)
    return True


def first_line(err: BaseException) -> str:
    """``Type: first line of the message`` of an unexpected error."""
    text = str(err).strip().splitlines()
    return f"{type(err).__name__}: {text[0]}" if text else type(err).__name__


def run_point(config_yaml: str, folder: str, threads: int = 1) -> dict:
    """Run one point: ``eofnn compare --config <folder>/point.yaml --out <folder>/run`` from an empty folder.

    Parameters
    ----------
    config_yaml : str
        The point's full resolved compare config.
    folder : str
        The point's folder (absolute); whatever is in it is removed first, so a rerun starts from scratch.
    threads : int
        Torch intra-op threads while the point runs (fixed, so results do not depend on where it runs).

    Returns
    -------
    dict
        ``status`` (``done`` or ``failed``), ``error`` (one line or ``None``), ``seconds`` and, when done,
        ``scenarios`` (the metrics of ``metrics.json``).
    """
    import torch  # here: ``eofnn sweep --help`` needs none of it

    from eofnn.cli.commands import USER_ERRORS, one_line, parse  # here: the sweep's --help needs none of compare
    from eofnn.cli.compare import compare

    out = Path(folder)
    if out.exists():
        shutil.rmtree(out)
    out.mkdir(parents=True)
    config = out / CONFIG_FILE
    config.write_text(config_yaml)
    previous_threads = torch.get_num_threads()
    torch.set_num_threads(threads)
    # BLAS threads too (numpy/HCIPy build the turbulence): summation order, hence the last bits, follows them.
    blas = threadpool_limits(threads)
    in_main_thread = threading.current_thread() is threading.main_thread()
    previous_sigint = signal.getsignal(signal.SIGINT) if in_main_thread else None
    start = time.perf_counter()
    error = None
    try:
        with open(out / LOG_FILE, "w") as log, contextlib.redirect_stdout(log), contextlib.redirect_stderr(log):
            try:
                parsed = parse(["compare", "--config", str(config), "--out", str(out / RUN_DIR), "--progress", "false"])
                compare(parsed.config, parsed.dump)
            except USER_ERRORS as err:  # a value compare refuses: its one line, as ``eofnn compare`` prints it
                error = one_line(err)
                print(f"{ERROR_PREFIX}{error}", file=log)
            except SystemExit:
                # Lightning answers Ctrl-C during training with sys.exit(1) (and ignores SIGINT from then on):
                # for the sweep it is the interruption it is.
                raise KeyboardInterrupt from None
            except Exception as err:  # a bug, not a bad value: keep the traceback in the log, one line in the status
                traceback.print_exc(file=log)
                error = first_line(err)
    finally:
        torch.set_num_threads(previous_threads)
        blas.restore_original_limits()
        if previous_sigint is not None:
            signal.signal(signal.SIGINT, previous_sigint)
    status = {"status": "failed" if error else "done", "error": error, "seconds": round(time.perf_counter() - start, 3)}
    write_atomic(out / STATUS_FILE, json.dumps(status, indent=1))
    if not error:
        status["scenarios"] = json.loads((out / RUN_DIR / "metrics.json").read_text())["scenarios"]
    return status


def record_failure(folder: str | Path, error: str) -> dict:
    """Mark a point failed for a reason outside compare (its worker died): the result :func:`run_point` gives."""
    status = {"status": "failed", "error": error, "seconds": None}
    out = Path(folder)
    out.mkdir(parents=True, exist_ok=True)
    write_atomic(out / STATUS_FILE, json.dumps(status, indent=1))
    return status


def _flat(node, prefix: str = "") -> dict[str, object]:
    if isinstance(node, dict) and node:
        flat = {}
        for key, value in node.items():
            flat.update(_flat(value, f"{prefix}.{key}" if prefix else str(key)))
        return flat
    return {prefix: node}


def config_changes(old_yaml: str, new_yaml: str, most: int = 3) -> str:
    """What differs between two resolved configs, on one line: ``evaluation.frames 300 -> 320, ...``."""
    import yaml

    try:
        old, new = _flat(yaml.safe_load(old_yaml) or {}), _flat(yaml.safe_load(new_yaml) or {})
    except yaml.YAMLError:
        return "its point.yaml is not valid YAML"
    missing = object()
    changes = [f"{key} {old.get(key, '(unset)')!r} -> {new.get(key, '(unset)')!r}"
               for key in sorted(set(old) | set(new)) if old.get(key, missing) != new.get(key, missing)]
    if not changes:
        return "its point.yaml differs only in layout"
    more = len(changes) - most
    return ", ".join(changes[:most]) + (f" and {more} more" if more > 0 else "")


def read_point(folder: Path, config_yaml: str) -> dict | None:
    """The result of a finished point (as :func:`run_point` returns it), or ``None`` if it has to run.

    Raises
    ------
    ConfigError
        If the folder holds a point run with another config (the base config changed since).
    """
    from eofnn.errors import ConfigError

    status_path, config_path = folder / STATUS_FILE, folder / CONFIG_FILE
    try:
        status = json.loads(status_path.read_text())
    except (OSError, json.JSONDecodeError):
        return None
    if status.get("status") != "done":
        return None  # failed points are retried on every restart
    old = config_path.read_text() if config_path.is_file() else ""
    if old != config_yaml:
        raise ConfigError(f"point {folder.name!r} in {str(folder.parent)!r} was run with another configuration (the "
                          f"base config changed: {config_changes(old, config_yaml)}): choose another --out, or pass "
                          "--overwrite true to discard the old points")
    try:
        status["scenarios"] = json.loads((folder / RUN_DIR / "metrics.json").read_text())["scenarios"]
    except (OSError, json.JSONDecodeError, KeyError):
        return None
    return status
