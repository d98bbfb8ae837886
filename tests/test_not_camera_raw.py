"""Issue 13, item 5 (part): a film-scanner NEF that LibRaw opens is refused
with a 415 naming what it is, on the REST API and in the CLI (no traceback)."""

from __future__ import annotations

import pytest

from .test_dng_render import real_file


def test_scanner_nef_is_a_415_naming_it():
    from fastapi.testclient import TestClient

    from service.app import app

    p = real_file("Nikon_uncompressed.nef")
    with TestClient(app) as c:
        r = c.post("/v1/analyze", files={"file": (p.name, p.read_bytes())})
    assert r.status_code == 415, r.text
    body = r.json()
    assert body["error"] == "not_camera_raw"
    assert "not a camera RAW: a scanned 8-bit RGB image" in body["detail"]


@pytest.mark.parametrize("command", ["analyze", "white-balance"])
def test_scanner_nef_in_the_cli(command, tmp_path, capsys):
    from service import cli

    p = real_file("Nikon_uncompressed.nef")
    argv = [command, str(p)] + ([str(tmp_path / "out.jpg"), "--format", "jpeg"] if command == "white-balance" else [])
    assert cli.main(argv) == 1
    out = capsys.readouterr()
    text = out.out + out.err
    assert "not a camera RAW: a scanned 8-bit RGB image" in text
    assert "Traceback" not in text
