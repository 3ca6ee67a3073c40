"""The style gate: ``ruff check`` over the package, the tests, the launch file and setup.py with
the project's ``ruff.toml`` (100 columns, pycodestyle, pyflakes' unused and undefined names,
import order). ``python -m ruff check --fix`` sorts imports; long lines are wrapped by hand."""
from pathlib import Path
import subprocess
import sys

ROOT = Path(__file__).resolve().parents[1]
CHECKED = ('soft_gripper_sdre', 'test', 'launch', 'setup.py')
RUFF = (sys.executable, '-m', 'ruff', 'check', '--no-cache', '--output-format', 'concise')


def test_the_tree_is_clean_under_ruff():
    r = subprocess.run([*RUFF, *CHECKED], cwd=ROOT, capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, (r.stdout + r.stderr)[-4000:]


def test_the_gate_finds_what_it_is_for(tmp_path):
    """The same command on a file with a long line, an unused import and unsorted imports names
    all three (the gate can fail)."""
    bad = tmp_path / 'bad.py'
    bad.write_text('import sys\nimport os\n\nX = "' + 'x' * 100 + '"\n', encoding='utf-8')
    r = subprocess.run([*RUFF, '--config', str(ROOT / 'ruff.toml'), str(bad)],
                       capture_output=True, text=True, timeout=120)
    assert r.returncode == 1
    for code in ('E501', 'F401', 'I001'):
        assert code in r.stdout, r.stdout
