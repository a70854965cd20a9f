"""Hostile stream folders (issue 33): an impossible sensor rate, region or image size in ``stream.json`` is one
``InputError`` naming the file, before any sequence is read."""

from __future__ import annotations

import json

import pytest

from detector.stream.data import read_stream
from mpchair.core.errors import InputError

GOOD = {"rate_hz": 10.0, "region": {"max_abs_dz": 1.5, "max_distance": 10.0, "half_fov": 0.78},
        "image_size": [640, 480], "sequences": {}}


@pytest.mark.parametrize("edit, message", [
    ({"rate_hz": 0}, "rate_hz: expected a sensor rate in (0, 1000] Hz, got 0.0"),
    ({"rate_hz": float("nan")}, "rate_hz: expected a sensor rate"),
    ({"rate_hz": -10}, "rate_hz: expected a sensor rate"),
    ({"rate_hz": 1e300}, "rate_hz: expected a sensor rate"),
    ({"region": {"max_abs_dz": 1.5, "max_distance": float("inf"), "half_fov": None}}, "region: expected positive"),
    ({"region": {"max_abs_dz": -1, "max_distance": 10.0, "half_fov": None}}, "region: expected positive"),
    ({"image_size": [0, 480]}, "image_size: expected a positive width and height"),
    ({"rate_hz": "fast"}, "malformed stream file (ValueError"),
])
def test_impossible_stream_metadata_is_refused(tmp_path, edit, message):
    (tmp_path / "stream.json").write_text(json.dumps({**GOOD, **edit}))
    with pytest.raises(InputError) as err:
        read_stream(tmp_path)
    assert str(err.value).startswith(f"{tmp_path / 'stream.json'}: {message}"), err.value


def test_a_sane_stream_file_gets_past_the_checks(tmp_path):
    """The checks can pass: the good metadata reaches the next check (no sequences)."""
    (tmp_path / "stream.json").write_text(json.dumps(GOOD))
    with pytest.raises(InputError, match="the stream has no sequences"):
        read_stream(tmp_path)


def test_non_utf8_stream_file_is_one_line(tmp_path):
    (tmp_path / "stream.json").write_bytes(b'{"rate_hz": "\xff"}')
    with pytest.raises(InputError, match=r"stream.json:1: not UTF-8 text \(byte 13 is 0xff\)"):
        read_stream(tmp_path)
