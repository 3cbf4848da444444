"""The README's Python example runs as written and does what it says."""

import re
from pathlib import Path

import numpy as np

from fusedmosaic.evaluation import frame_errors, mosaic_error

README = Path(__file__).resolve().parents[1] / "README.md"


def test_readme_live_loop_example():
    code = re.findall(r"## Python, live\n\n```python\n(.*?)```", README.read_text(), re.S)
    assert len(code) == 1, "README.md: the '## Python, live' example is missing"
    namespace: dict = {}
    exec(compile(code[0], "README.md", "exec"), namespace)  # noqa: S102 - our own README
    final, scene = namespace["final"], namespace["scene"]
    assert sorted(final) == list(range(60))
    G = np.stack([final[k] for k in range(60)])
    # the sequential method on the simulator: e_M well under a pixel (SYN: ~0.1 px)
    assert mosaic_error(frame_errors(G, scene.homographies, *scene.size)) < 1.0


def test_readme_cli_lines_use_existing_options():
    """Every `fusedmosaic ...` line in the README's command block parses with the CLI."""
    from fusedmosaic.cli import build_parser

    block = re.findall(r"## Command line\n\n```bash\n(.*?)```", README.read_text(), re.S)[0]
    parser = build_parser()
    for line in block.splitlines():
        args = line.split("#")[0].split()[1:]
        # optional parts written [a|b] in the README: keep the first alternative
        args = [a.strip("[]").split("|")[0] for a in args if a not in ("...", "OUT2")]
        parser.parse_args(args)


def test_one_version_in_pyproject_the_package_and_the_core():
    """The version is written in pyproject.toml and python/fusedmosaic/__init__.py; the core
    gets it from the build (SKBUILD_PROJECT_VERSION): the three agree."""
    import fusedmosaic
    from fusedmosaic import _core

    pyproject = (README.parent / "pyproject.toml").read_text()
    version = re.search(r'^version = "([^"]+)"', pyproject, re.M)
    assert version is not None
    assert fusedmosaic.__version__ == _core.__version__ == version.group(1)
