"""``python -m eabc.experiments.worker ROOT JOB_JSON``: one sweep job in a fresh process."""

from __future__ import annotations

import json
import sys

from eabc.experiments.sweep import execute


def main(argv: list[str] | None = None) -> None:
    argv = sys.argv[1:] if argv is None else argv
    root, payload = argv
    for summary in execute(json.loads(payload), root):
        print(json.dumps(summary), flush=True)


if __name__ == "__main__":
    main()
