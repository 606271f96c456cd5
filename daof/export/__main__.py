"""``python -m daof.export CHECKPOINT --out DIR [--format torch,aoti,onnx]``: export a trained filter.

See docs/deploy.md.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from daof.export import FORMATS, export_filter, file_digest


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        prog="python -m daof.export", description="Export a trained filter's streaming step."
    )
    parser.add_argument("checkpoint", type=Path, help="a saved filter (best.pt, final.pt) or a training checkpoint.pt")
    parser.add_argument("--out", type=Path, required=True, help="directory to write the artifacts and contract.json")
    parser.add_argument(
        "--format", default="torch,onnx", help=f"comma-separated, of {','.join(FORMATS)} (default torch,onnx)"
    )
    args = parser.parse_args(argv)
    formats = [fmt.strip() for fmt in args.format.split(",") if fmt.strip()]
    from daof.filters.learned import load_filter  # after argument errors: torch is slow to import
    from daof.filters.learned.uncertainty import head_path

    try:
        filt = load_filter(args.checkpoint)
        source = {"checkpoint": args.checkpoint.name, "sha256": file_digest(args.checkpoint)}
        if filt.uncertainty is not None:  # attached by load_filter: σ is exported too
            head = head_path(args.checkpoint)
            source |= {"uncertainty_head": head.name, "uncertainty_head_sha256": file_digest(head)}
        info = export_filter(filt, args.out, formats, source)
    except (ValueError, FileNotFoundError) as error:
        print(f"daof.export: {error}", file=sys.stderr)
        return 2
    for fmt, name in info["files"].items():
        print(f"{fmt}: {args.out / name}")
    if "std_source" in info:
        print(f"std: the error std per state, from {info['source']['uncertainty_head']}")
    print(f"contract: {args.out / 'contract.json'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
