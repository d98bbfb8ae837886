"""Issue 29, item 1: the README's five-minute tour runs as written.

Every code block of "A five-minute tour" is run here on the real CinemaDNG
(copied as ``IMG_0001.dng`` into a temporary folder, the tour's working
folder): the command-line block and the REST block with bash (``set -e``
and ``pipefail``: any failing command fails the test), the REST block
against ``python -m service`` started as the README starts it, the Python
block with this interpreter. The only substitutions are the interpreter
(``.venv/bin/wandell`` is ``python -m service.cli`` of this checkout, since
the venv's console script may belong to another checkout) and the server's
port (a free one instead of 8000). The two commands are checked against
``.ci/run``, and the docs pages the README links to exist."""

from __future__ import annotations

import os
import re
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from .conftest import running_server, shared_file, unavailable

ROOT = Path(__file__).resolve().parents[1]
README = (ROOT / "README.md").read_text(encoding="utf-8")
#: Pages other work in progress adds (issues 27, 28, 30, 31): linked now, present after their merge.
PENDING = {"docs/reliability.md", "docs/limits.md", "docs/demosaic.md", "docs/surfaces.md", "docs/mixed_light.md"}
SERVE = "python3 -m venv .venv && .venv/bin/pip install -e . && .venv/bin/python -m service"
TEST = "python3 -m venv .venv && .venv/bin/pip install -q -e '.[test]' && .venv/bin/python -m pytest"


def _blocks(text: str) -> list[tuple[str, str]]:
    return re.findall(r"```(\w+)\n(.*?)```", text, flags=re.S)


def _tour() -> dict:
    section = README.split("## A five-minute tour", 1)[1].split("\n## ", 1)[0]
    blocks = _blocks(section)
    out = {"cli": [b for lang, b in blocks if lang == "bash" and "wandell" in b],
           "rest": [b for lang, b in blocks if lang == "bash" and "curl" in b],
           "python": [b for lang, b in blocks if lang == "python"]}
    assert all(len(v) == 1 for v in out.values()) and len(blocks) == 3, blocks
    return {k: v[0] for k, v in out.items()}


@pytest.fixture()
def folder(tmp_path):
    shutil.copy(shared_file("data/raw/Blackmagic.dng"), tmp_path / "IMG_0001.dng")
    return tmp_path


def _env():
    return {**os.environ, "PYTHONPATH": str(ROOT) + os.pathsep + os.environ.get("PYTHONPATH", "")}


def _bash(script: str, cwd: Path) -> subprocess.CompletedProcess:
    return subprocess.run(["bash", "-c", "set -euo pipefail\n" + script], cwd=cwd, env=_env(),
                          capture_output=True, text=True, timeout=900)


def test_the_readme_is_short_and_keeps_its_two_commands():
    assert len(README.splitlines()) <= 300
    commands = [b.strip() for lang, b in _blocks(README) if lang == "bash" and b.strip().startswith("python3 -m venv")]
    assert commands == [SERVE, TEST]
    ci = (ROOT / ".ci" / "run").read_text(encoding="utf-8").strip().splitlines()
    assert ci[-1] == TEST, "README's test command and .ci/run's differ"


def test_the_docs_pages_it_links_exist():
    links = set(re.findall(r"`(docs/[\w.-]+\.md|CHANGELOG\.md)`", README))
    assert {"docs/accuracy.md", "docs/speed.md", "docs/robustness.md", "docs/benchmarks.md", "CHANGELOG.md"} <= links
    missing = {p for p in links if not (ROOT / p).is_file()}
    assert missing <= PENDING, missing - PENDING


def test_the_command_line_tour(folder):
    script = _tour()["cli"].replace(".venv/bin/wandell", f"{sys.executable} -m service.cli")
    r = _bash(script, folder)
    assert r.returncode == 0, r.stderr[-3000:]
    assert '"illuminant"' in r.stdout                         # wandell analyze's JSON
    assert (folder / "IMG_0001.tif").read_bytes()[:4] == b"II*\x00"
    assert (folder / "IMG_0001.jpg").read_bytes()[:2] == b"\xff\xd8"
    assert 'crs:Temperature="' in (folder / "IMG_0001.xmp").read_text(encoding="utf-8")
    rows = (folder / "surfaces.csv").read_text(encoding="utf-8").splitlines()
    assert rows[0].startswith("kind,where,warnings,400") and len(rows) == 1 + 4 * 6   # wandell surfaces' grid
    assert (folder / "corrected" / "IMG_0001.jpg").read_bytes()[:2] == b"\xff\xd8"


def test_the_rest_tour(folder):
    for tool in ("curl", "jq"):
        if shutil.which(tool) is None:
            unavailable(f"{tool} is not installed (apt-get install {tool}); the README's REST examples use it")
    with running_server({"data_dir": folder / "data"}) as (base, _, log):
        r = _bash(_tour()["rest"].replace("http://127.0.0.1:8000", base), folder)
        assert r.returncode == 0, (r.stderr[-3000:], open(log).read()[-3000:])
        cct = float(r.stdout.splitlines()[0])
        assert 4000 < cct < 5200, cct                          # the CinemaDNG's light (4580 K)
        assert (folder / "corrected.jpg").read_bytes()[:2] == b"\xff\xd8"
        assert (folder / "IMG_0001.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
        assert '"deleted":true' in r.stdout.replace(" ", "")   # the DELETE removed the batch
        assert not any((folder / "data" / "batches").iterdir())


def test_the_python_tour(folder):
    (folder / "tour.py").write_text(_tour()["python"], encoding="utf-8")
    r = subprocess.run([sys.executable, "tour.py"], cwd=folder, env=_env(), capture_output=True, text=True,
                       timeout=900)
    assert r.returncode == 0, r.stderr[-3000:]
    lines = r.stdout.splitlines()
    assert lines[-1] == "(1, 31)" and 0 <= float(lines[1]) <= 1, lines
