"""The README's example as a new installation meets it: a fresh process with an empty numba cache
(a new ``NUMBA_CACHE_DIR``), timing import, a learnable curv step at 2048x1024 RGB → 257x129, a
fixed-layout forward and a call with physics (see docs/speed.md, "The first call"). The code run
is ``layoutwarp.experiments.firstcalls.README_EXAMPLE``, which ``layoutwarp bench`` times too.

    python examples/first_call.py [--mode background|wait|off]
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile

from layoutwarp.experiments.firstcalls import README_EXAMPLE


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--mode", choices=("background", "wait", "off"), default="background")
    args = ap.parse_args()
    with tempfile.TemporaryDirectory() as cache:
        env = {**os.environ, "NUMBA_CACHE_DIR": cache, "LAYOUTWARP_JIT": args.mode}
        res = subprocess.run([sys.executable, "-c", README_EXAMPLE], env=env, capture_output=True, text=True)
    sys.stderr.write(res.stderr)
    if res.returncode == 0:
        out = json.loads(res.stdout.strip().splitlines()[-1])
        steps = "; ".join(f"{name} {s:.1f} s" for name, s in out["steps"].items())
        print(f"{steps}; in all {out['total']:.1f} s")
    return res.returncode


if __name__ == "__main__":
    sys.exit(main())
