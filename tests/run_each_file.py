"""Run every tests/test_*.py on its own (a fresh pytest process per file) and report the ones
that fail alone. Usage, from the repository root:

    python tests/run_each_file.py                 # all files, random order inside each file
    python tests/run_each_file.py test_mesh_io    # only files whose name contains a word

Exit status 1 if any file fails alone. Not collected by pytest (no test_ prefix).
"""

from __future__ import annotations

import subprocess
import sys
import time
from pathlib import Path

TESTS = Path(__file__).resolve().parent


def main(words: list[str]) -> int:
    files = sorted(p for p in TESTS.glob("test_*.py") if not words or any(w in p.name for w in words))
    failed = []
    for path in files:
        start = time.perf_counter()
        proc = subprocess.run([sys.executable, "-m", "pytest", "-n", "0", "-p", "no:cacheprovider", str(path)],
                              cwd=TESTS.parent, capture_output=True, text=True)
        took = time.perf_counter() - start
        lines = proc.stdout.strip().splitlines()
        last = next((ln for ln in reversed(lines) if " in " in ln and ("passed" in ln or "failed" in ln
                                                                    or "error" in ln or "skipped" in ln)),
                    lines[-1] if lines else "(no output)")
        print(f"{'ok  ' if proc.returncode in (0, 5) else 'FAIL'} {path.name:40s} {took:7.1f}s  {last}", flush=True)
        if proc.returncode not in (0, 5):                  # 5: nothing collected
            failed.append(path.name)
            print(proc.stdout[-3000:], proc.stderr[-2000:], sep="\n", flush=True)
    print(f"{len(files) - len(failed)}/{len(files)} files pass alone" + (f"; failing: {failed}" if failed else ""))
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
