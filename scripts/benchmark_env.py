"""Benchmark GraspClutter-v1 (same as `rtv3 benchmark-env`); prints medians."""

import sys

from rtv3_maniskill.cli import main

if __name__ == "__main__":
    sys.exit(main(["benchmark-env", *sys.argv[1:]]))
