#!/usr/bin/env bash
# CI: eofnn works outside a checkout. Build the wheel from the files git would commit, install it into a fresh venv
# (torch first, the build scripts/setup.sh pins, then the wheel and its dependencies), and from an empty folder run a
# config that ships with it by name (eofnn/configs/tiny.yaml) and check that a bundled config's `scenario:
# realistic.yaml` is found among the bundled ones. Exits non-zero at the first step that fails.
set -euo pipefail
cd "$(dirname "$0")/.."
root=$PWD
start=$SECONDS
TORCH=$(sed -n 's/^TORCH="\(.*\)"$/\1/p' scripts/setup.sh)
work=$(mktemp -d "${TMPDIR:-/tmp}/eofnn-wheel.XXXXXX")
trap 'rm -rf "$work"' EXIT
say() { echo "check_wheel: $* ($((SECONDS - start)) s)" >&2; }

# The tracked files and new ones git does not ignore, nothing a local build left behind (build/, *.egg-info).
mkdir "$work/src"
git ls-files -z --cached --others --exclude-standard | (cd "$root" && tar --null -T - --ignore-failed-read -cf -) \
    | tar -C "$work/src" -xf -
python3 -m venv "$work/venv"
py="$work/venv/bin/python"
# pip's status is the function's; its warnings about local index folders that do not exist are left out.
pip() { "$py" -m pip install -q "$@" 2> >(grep -v "^WARNING: Location .* is ignored" >&2); }
pip "$TORCH"
"$py" -m pip wheel -q --no-deps -w "$work/dist" "$work/src"
pip "$work"/dist/eofnn-*.whl
say "built and installed $(basename "$work"/dist/eofnn-*.whl) with $TORCH"

mkdir "$work/empty"
cd "$work/empty"
unset PYTHONPATH
installed=$("$py" -c 'import eofnn; print(eofnn.__file__)')
case "$installed" in "$work/venv/"*) ;; *) echo "check_wheel: eofnn imported from $installed, not the venv" >&2; exit 1 ;; esac
listed=$("$work/venv/bin/eofnn" configs list)
grep -q "^tiny " <<<"$listed" || { echo "check_wheel: eofnn configs list does not list tiny" >&2; exit 1; }
printed=$("$work/venv/bin/eofnn" compare --config realistic_small --out results/x --print_config 2>"$work/said")
grep -q "n_across: 40" <<<"$printed" && grep -q "eofnn/configs/realistic_small.yaml (eofnn's own" "$work/said" \
    || { echo "check_wheel: the bundled realistic_small (scenario: realistic.yaml) was not found by name" >&2; exit 1; }
OMP_NUM_THREADS=${OMP_NUM_THREADS:-1} "$work/venv/bin/eofnn" compare --config tiny --out results/tiny
for file in metrics.json results.md config.yaml; do
    [ -s "results/tiny/$file" ] || { echo "check_wheel: results/tiny/$file was not written" >&2; exit 1; }
done
say "eofnn compare --config tiny ran from an empty folder with the installed wheel"
