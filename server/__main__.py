"""``python -m server [--host ... --port ... --model ... --data-dir ...]``: the same as ``fastgha serve``."""

import sys

from fastgha_core.cli import main

if __name__ == "__main__":
    sys.exit(main(["serve", *sys.argv[1:]]))
