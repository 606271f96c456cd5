"""Write (or check) README.md's results summary from the committed reports' results.json.

.venv/bin/python scripts/results_summary.py          # rewrite the block in README.md
.venv/bin/python scripts/results_summary.py --check  # exit 1 if README.md's block is out of date
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from daof.evaluate.summary import replace_block, summary_markdown

ROOT = Path(__file__).resolve().parents[1]


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--check", action="store_true", help="only check that README.md is up to date")
    args = parser.parse_args()
    readme = ROOT / "README.md"
    text = readme.read_text()
    updated = replace_block(text, summary_markdown(ROOT))
    if args.check:
        if updated != text:
            print("README.md's results summary is out of date: run scripts/results_summary.py", file=sys.stderr)
            return 1
        return 0
    readme.write_text(updated)
    return 0


if __name__ == "__main__":
    sys.exit(main())
