"""docs/python.md's examples, run as written (each ```python block, in order, in one script)."""
import os
import re
import subprocess
import sys
from pathlib import Path

import mrskin

DOC = Path(os.environ.get("MRSKIN_SOURCE_DIR", Path(__file__).parents[2])) / "docs" / "python.md"


def test_the_example_runs_as_written(tmp_path):
    blocks = re.findall(r"^```python\n(.*?)^```", DOC.read_text(), flags=re.S | re.M)
    assert blocks, f"no python block in {DOC}"
    script = tmp_path / "example.py"
    script.write_text("\n".join(blocks))
    # The module this test imported, wherever the script runs from.
    here = str(Path(mrskin.__file__).resolve().parent)
    env = dict(os.environ, MPLBACKEND="Agg", PYTHONPATH=os.pathsep.join([here, os.environ.get("PYTHONPATH", "")]))
    run = subprocess.run([sys.executable, str(script)], cwd=tmp_path, env=env, capture_output=True, text=True)
    assert run.returncode == 0, run.stdout + run.stderr
    assert "hand" in run.stdout
