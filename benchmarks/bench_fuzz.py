"""The long run of the file-reader fuzzing (tests/test_fuzz_readers.py); exits non-zero
on a failure, with Hypothesis' shrunk example.

    .venv/bin/python benchmarks/bench_fuzz.py [--examples 5000]

CI runs the same property on a fixed set of a few hundred cases; this draws EXAMPLES new
ones (a new random seed every run): corrupted run, estimate and plan files handed to
every command that reads them, which must accept each file or exit 2 with one line
naming it (never a traceback, never the bug status 3).  About 20 ms per case.
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--examples", type=int, default=5000, help="cases to draw (default 5000)")
    args = ap.parse_args(argv)
    print(f"load average {os.getloadavg()[0]:.2f}; {args.examples} cases", flush=True)
    t0 = time.perf_counter()
    res = subprocess.run([sys.executable, "-m", "pytest", "-q", "-x", "tests/test_fuzz_readers.py"], cwd=ROOT,
                         env={**os.environ, "TACEST_FUZZ_EXAMPLES": str(args.examples)})
    print(f"{'passed' if res.returncode == 0 else 'FAILED'}: {args.examples} cases in "
          f"{time.perf_counter() - t0:.0f} s")
    return res.returncode


if __name__ == "__main__":
    sys.exit(main())
