"""Apply the deliberate bugs of scripts/mutants.toml one at a time and see whether the CI suite kills each.

Each mutant replaces one line in the working tree, runs its listed test files (``pytest -x``, the CI
selection: not slow) and restores the file, also on an interruption. A mutant a subset kills is
killed by the whole suite; a survivor of its subset is run against the whole CI suite before it is
called a survivor. Run it on a clean tree, with nothing else testing in it:

    .venv/bin/python scripts/mutation_check.py [--only N ...] [--json out.json]
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import time
from pathlib import Path

import tomllib

ROOT = Path(__file__).resolve().parents[1]
PYTEST = [sys.executable, "-m", "pytest", "-q", "-x", "-m", "not slow", "-p", "no:cacheprovider"]


def load(path: Path) -> list[dict]:
    mutants = tomllib.loads(path.read_text())["mutant"]
    for m in mutants:
        lines = (ROOT / m["file"]).read_text().split("\n")
        hits = [i for i, line in enumerate(lines) if line == m["original"]]
        if len(hits) < m.get("nth", 1):
            raise SystemExit(f"{m['file']}: line not found ({m.get('nth', 1)}x): {m['original']!r}")
        m["line"] = hits[m.get("nth", 1) - 1] + 1
    return mutants


def run_tests(tests: list[str], timeout: float) -> tuple[bool, float]:
    """(killed, seconds): the tests failed or errored (pytest exit 1 or 2; 5 = nothing collected is an error)."""
    start = time.perf_counter()
    try:
        done = subprocess.run([*PYTEST, *tests], cwd=ROOT, capture_output=True, text=True, timeout=timeout)
    except subprocess.TimeoutExpired:
        return True, time.perf_counter() - start  # a hang is a detected change too
    if done.returncode == 5:
        raise SystemExit(f"no tests collected for {tests}")
    return done.returncode != 0, time.perf_counter() - start


def check(m: dict, confirm: bool, timeout: float) -> dict:
    path = ROOT / m["file"]
    original = path.read_text()
    lines = original.split("\n")
    lines[m["line"] - 1] = m["mutated"]
    try:
        path.write_text("\n".join(lines))
        killed, seconds = run_tests(m["tests"], timeout)
        by = "subset"
        if not killed and confirm:
            killed, more = run_tests([], 4 * timeout)
            seconds += more
            by = "whole suite"
    finally:
        path.write_text(original)
    return {"file": m["file"], "line": m["line"], "breaks": m["breaks"], "killed": killed, "by": by, "s": seconds}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--list", type=Path, default=ROOT / "scripts" / "mutants.toml")
    ap.add_argument("--only", type=int, nargs="*", help="1-based indices of the mutants to run")
    ap.add_argument("--no-confirm", action="store_true", help="do not run the whole suite on a subset's survivors")
    ap.add_argument("--timeout", type=float, default=600.0, help="seconds per subset run")
    ap.add_argument("--json", type=Path, help="write the results here")
    args = ap.parse_args()
    mutants = load(args.list)
    chosen = [(i, m) for i, m in enumerate(mutants, 1) if not args.only or i in args.only]
    results = []
    for i, m in chosen:
        r = check(m, not args.no_confirm, args.timeout)
        results.append({"id": i, **r})
        verdict = f"killed ({r['by']})" if r["killed"] else "SURVIVED"
        print(f"[{i:2d}] {verdict:22s} {r['s']:6.1f} s  {m['file']}:{r['line']}  {m['breaks']}", flush=True)
    killed = sum(r["killed"] for r in results)
    print(f"kill rate: {killed}/{len(results)} = {100 * killed / len(results):.1f} %")
    for r in results:
        if not r["killed"]:
            print(f"survivor [{r['id']}] {r['file']}:{r['line']}: {r['breaks']}")
    if args.json:
        args.json.write_text(json.dumps({"killed": killed, "total": len(results), "results": results}, indent=2))


if __name__ == "__main__":
    main()
