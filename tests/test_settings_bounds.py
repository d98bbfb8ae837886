"""Out-of-range ``WANDELL_*`` settings stop the server and the CLI in words.

Probe round 7 (``docs/probe_round7.md``, "Noticed"): ``WANDELL_MAX_UPLOAD_BYTES=-1``
started a server that refused every upload, ``WANDELL_BODY_TIMEOUT=nan`` one whose
time-outs never fire. The settings now carry their ranges (``service.settings``) and
both entry points exit with status 2 naming the variable, without a traceback.
"""

from __future__ import annotations

import os
import subprocess
import sys

import pytest
from pydantic import ValidationError

from service.settings import Settings, settings_problem


def _env(**extra):
    env = {k: v for k, v in os.environ.items() if not k.upper().startswith("WANDELL_")}
    env.update(extra)
    return env


@pytest.mark.parametrize("name, value, words", [
    ("WANDELL_MAX_UPLOAD_BYTES", "-1", "greater than or equal to 1"),
    ("WANDELL_BODY_TIMEOUT", "nan", "finite"),
    ("WANDELL_BODY_TIMEOUT", "0", "greater than 0"),
    ("WANDELL_MAX_BATCH_ITEMS", "0", "greater than or equal to 1"),
    ("WANDELL_PORT", "70000", "less than or equal to 65535"),
])
def test_an_out_of_range_setting_is_refused_naming_it(name, value, words, monkeypatch):
    monkeypatch.setenv(name, value)
    with pytest.raises(ValidationError) as e:
        Settings()
    text = settings_problem(e.value)
    assert name in text and repr(value) in text and words in text, text


def test_zero_means_automatic_where_the_docs_say_so(monkeypatch):
    for name in ("WANDELL_MAX_CONCURRENT_WORK", "WANDELL_BATCH_WORKERS", "WANDELL_MAX_CONNECTIONS",
                 "WANDELL_BODY_DEADLINE", "WANDELL_SEND_TIMEOUT"):
        monkeypatch.setenv(name, "0")
    monkeypatch.setenv("WANDELL_BATCH_RESULT_RETENTION", "-1")       # negative: kept for ever (documented)
    monkeypatch.setenv("WANDELL_BATCH_INPUT_RETENTION", "-1")        # the same (service.batch.runner)
    s = Settings()
    assert (s.max_concurrent_work, s.batch_workers, s.max_connections, s.body_deadline, s.send_timeout,
            s.batch_result_retention, s.batch_input_retention) == (0, 0, 0, 0.0, 0.0, -1.0, -1.0)


def test_the_server_stops_at_start_in_words():
    r = subprocess.run([sys.executable, "-m", "service", "--port", "0"], capture_output=True, text=True,
                       timeout=60, env=_env(WANDELL_MAX_UPLOAD_BYTES="-1"))
    assert r.returncode == 2, (r.returncode, r.stderr)
    assert "WANDELL_MAX_UPLOAD_BYTES='-1'" in r.stderr and "Traceback" not in r.stderr, r.stderr


def test_the_cli_stops_in_words(tmp_path):
    photo = tmp_path / "a.dng"
    photo.write_bytes(b"II*\x00")          # never read: the settings are checked first
    r = subprocess.run([sys.executable, "-m", "service.cli", "analyze", str(photo)], capture_output=True,
                       text=True, timeout=60, env=_env(WANDELL_MAX_PIXELS="0"))
    assert r.returncode == 2, (r.returncode, r.stderr)
    assert "WANDELL_MAX_PIXELS='0'" in r.stderr and "Traceback" not in r.stderr, r.stderr
