"""experiments/ commits inputs, scripts, summaries, pages and figures; raw runs live in the ignored experiments/runs/.

(a) every path the pages name into the repository is a tracked file (or folder), and every command they show writes
    into experiments/runs/ and reads committed inputs; (b) no tracked file under experiments/ is a raw output; (c)
    experiments/README.md regenerates byte for byte from the committed summaries alone.
"""

from __future__ import annotations

import fnmatch
import re
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
EXPERIMENTS = ROOT / "experiments"


def _tracked() -> list[str]:
    try:
        out = subprocess.run(["git", "ls-files"], cwd=ROOT, capture_output=True, text=True, check=True).stdout
    except (OSError, subprocess.CalledProcessError):
        return []  # not a git checkout: the tests below skip
    return out.splitlines()


TRACKED = _tracked()
FILES = set(TRACKED)
FOLDERS = {str(p) for f in TRACKED for p in Path(f).parents if str(p) != "."}
PAGES = sorted(f for f in TRACKED if f.endswith(".md") and (f.startswith(("experiments/", "docs/")) or f == "README.md"))


def _resolves(path: str) -> bool:
    """A tracked file, a folder holding tracked files, or a glob matching one."""
    path = path.rstrip("/")
    if "*" in path:
        return any(fnmatch.fnmatch(f, path) for f in TRACKED)
    return path in FILES or path in FOLDERS


def _candidates(page: str, target: str) -> list[str]:
    """``target`` as written on ``page``: relative to the page's folder, or (for code spans) to the repository root."""
    here = (ROOT / page).parent
    paths = [(here / target), (ROOT / target)]
    out = []
    for p in paths:
        try:
            out.append(str(p.resolve().relative_to(ROOT)) + ("/" if target.endswith("/") else ""))
        except ValueError:  # outside the repository
            out.append(str(p))
    return out


def _references(page: str) -> list[tuple[str, bool]]:
    """(target, is a markdown link) for every link and every path-like code span on ``page``."""
    text = (ROOT / page).read_text()
    links = [(t.split("#")[0], True) for t in re.findall(r"\]\(([^)\s]+)\)", text) if not re.match(r"[a-z]+:|#", t)]
    spans = [(t, False) for t in re.findall(r"`([^`\s]+)`", text)
             if "/" in t and not re.search(r"[<>{}$(),:=]", t) and not t.startswith(("-", "."))]
    if not page.startswith("experiments/"):  # elsewhere only what points into experiments/
        spans = [(t, f) for t, f in spans if t.startswith("experiments/")]
        spans += [(t.rstrip(".,;"), False) for t in re.findall(r"(?<![\w/])experiments/[\w./*-]*", text)]
    return links + spans


@pytest.mark.skipif(not TRACKED, reason="not a git checkout")
@pytest.mark.parametrize("page", PAGES)
def test_every_path_a_page_names_is_tracked(page):
    broken = []
    for target, is_link in _references(page):
        candidates = _candidates(page, target)[:1] if is_link else _candidates(page, target)
        if any(c.startswith("experiments/runs/") or c.rstrip("/") == "experiments/runs" for c in candidates):
            continue  # the raw runs: ignored by design
        if not page.startswith("experiments/") and not candidates[0].startswith("experiments/"):
            continue  # outside experiments/ other tests watch the links
        if not any(_resolves(c) for c in candidates):
            broken.append(target)
    assert not broken, f"{page} names paths that are not tracked: {sorted(set(broken))}"


COMMANDS = ["README.md", "experiments/reproduce.sh", "experiments/interop/run.sh"]


def _committed(path: str) -> str:
    """``path`` as git tracks it: through the links of the checkout (``configs/`` -> ``eofnn/configs/``)."""
    try:
        return str((ROOT / path).resolve().relative_to(ROOT))
    except ValueError:  # a link out of the repository
        return path


@pytest.mark.skipif(not TRACKED, reason="not a git checkout")
def test_every_shown_command_writes_to_runs_and_reads_committed_inputs():
    pages = [p for p in PAGES if p.count("/") <= 1]  # not the runs' own results.md: they record what was run
    sources = sorted({*pages, *COMMANDS, *(f for f in TRACKED if f.startswith(("eofnn/configs/", "examples/")))})
    wrong_out, missing_in = [], []
    for source in sources:
        text = (ROOT / source).read_text().replace("$r/", "experiments/runs/").replace("$x/", "experiments/")
        text = re.sub(r"\\\n\s*#?\s*", " ", text)  # continuation lines
        for out in re.findall(r"--out\s+(experiments/\S+?)[`'\s]", text):
            if not out.startswith("experiments/runs/"):
                wrong_out.append(f"{source}: --out {out}")
        for flag, path in re.findall(r"(--config|--grid|--scenario)\s+((?:experiments|configs)/[\w./-]+\.yaml)", text):
            if "$" not in path and _committed(path) not in FILES:
                missing_in.append(f"{source}: {flag} {path}")
    assert not wrong_out, f"raw output outside experiments/runs/: {wrong_out}"
    assert not missing_in, f"inputs that are not committed: {missing_in}"


RAW_NAMES = {"config.yaml", "metrics.json", "robustness.json", "pareto.json", "sweep.csv", "sweep.yaml", "point.yaml",
             "status.json", "log.txt", ".eofnn-outputs"}
RAW_SUFFIXES = (".ckpt", ".ckpt.yaml", ".npz", ".fits", ".pt", ".pth")


@pytest.mark.skipif(not TRACKED, reason="not a git checkout")
@pytest.mark.cli
def test_no_raw_output_is_tracked_under_experiments():
    raw = [f for f in TRACKED if f.startswith("experiments/")
           and ("/points/" in f or f.startswith("experiments/runs/") or Path(f).name in RAW_NAMES
                or f.endswith(RAW_SUFFIXES))]
    assert not raw, f"raw outputs belong in experiments/runs/ (ignored): {raw[:10]}"
    allowed = (".md", ".png", ".py", ".sh", ".yaml")
    other = [f for f in TRACKED if f.startswith("experiments/") and not f.endswith(allowed)
             and Path(f).name not in ("summary.json", "generated.json")]
    assert not other, f"unexpected files under experiments/: {other}"
    ignored = subprocess.run(["git", "check-ignore", "-q", "experiments/runs/paper/metrics.json"], cwd=ROOT)
    assert ignored.returncode == 0, "experiments/runs/ must be ignored"


@pytest.mark.skipif(not TRACKED, reason="not a git checkout")
def test_every_collected_experiment_has_a_committed_summary():
    sys.path.insert(0, str(EXPERIMENTS))
    try:
        import summarise
    finally:
        sys.path.remove(str(EXPERIMENTS))
    names = [*summarise.COMPARES, *(f"sweeps/{s}" for s in summarise.SWEEPS),
             *(f"interop/{r}" for r in summarise.INTEROP), *summarise.JSONS, *summarise.MAPS]
    assert [n for n in names if f"experiments/{n}/summary.json" not in FILES] == []


@pytest.mark.skipif(not TRACKED, reason="not a git checkout")
@pytest.mark.cli
def test_the_page_regenerates_from_the_committed_summaries_alone(tmp_path):
    copy = tmp_path / "experiments"  # the committed files only (no runs/), figures left out
    for f in TRACKED:
        if f.startswith("experiments/") and not f.endswith(".png"):
            (tmp_path / f).parent.mkdir(parents=True, exist_ok=True)
            shutil.copyfile(ROOT / f, tmp_path / f)
    out = tmp_path / "README.md"
    done = subprocess.run([sys.executable, str(copy / "make_report.py"), "--out", str(out)], cwd=tmp_path,
                          capture_output=True, text=True)
    assert done.returncode == 0, done.stderr
    assert out.read_bytes() == (EXPERIMENTS / "README.md").read_bytes(), \
        "experiments/README.md differs from what make_report.py writes from the summaries: rerun it"
