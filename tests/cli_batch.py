"""Run ``main.py``'s command line several times in ONE interpreter (torch and Hydra imported once).

``python tests/cli_batch.py CASES.json`` reads a JSON list of argument lists, runs ``main.cli()`` on
each as ``python main.py ARGS...`` would (from the repository root, stderr captured, ``SystemExit``
caught) and prints a JSON list of ``{"returncode", "stderr"}``. For tests of the command line's error
paths, which would otherwise start a Python process (and import torch) per case.
"""

import contextlib
import io
import json
import os
import subprocess
import sys
from pathlib import Path
from typing import Dict, List

REPO = Path(__file__).resolve().parents[1]


def run_batch(cases: List[List[str]], folder: Path) -> List[Dict[str, object]]:
    """``{"returncode", "stderr"}`` of ``python main.py ARGS...`` for each argument list of ``cases``, all
    run in one subprocess (``folder`` holds the list as ``cases.json``)."""
    folder.mkdir(parents=True, exist_ok=True)
    (folder / "cases.json").write_text(json.dumps(cases))
    env = dict(os.environ, L3D_NO_PROGRESS="1")
    out = subprocess.run([sys.executable, __file__, str(folder / "cases.json")], capture_output=True, text=True,
                         env=env, timeout=600)
    assert out.returncode == 0, out.stderr
    return json.loads(out.stdout.strip().splitlines()[-1])


def main() -> None:
    cases = json.loads(Path(sys.argv[1]).read_text())
    sys.path.insert(0, str(REPO))
    os.chdir(REPO)
    import main as entry

    entry.main.__wrapped__.__module__ = "__main__"   # Hydra finds conf/ beside main.py, as for the script
    results = []
    for args in cases:
        sys.argv = [str(REPO / "main.py"), *args]
        err, code = io.StringIO(), 0
        with contextlib.redirect_stderr(err):
            try:
                entry.cli()
            except SystemExit as exit_:
                code = exit_.code if isinstance(exit_.code, int) else (0 if exit_.code is None else 1)
        results.append({"returncode": code, "stderr": err.getvalue()})
    print(json.dumps(results))


if __name__ == "__main__":
    main()
