"""The real-capture location: $SLWARP_DATA, else ../shared/data beside the repository (slwarp.scans.data)."""
from __future__ import annotations

from pathlib import Path

import pytest

from slwarp.scans import data


def test_the_variable_names_the_folder(tmp_path, monkeypatch):
    (tmp_path / "procam_chessboard").mkdir()
    monkeypatch.setenv("SLWARP_DATA", str(tmp_path))
    assert data.data_dir() == tmp_path
    assert data.real_capture_dir("procam_chessboard") == tmp_path / "procam_chessboard"


def test_default_is_shared_data_beside_the_repository(monkeypatch):
    monkeypatch.delenv("SLWARP_DATA", raising=False)
    repo = Path(__file__).resolve().parents[1]
    assert data.data_dir() == repo.parent / "shared" / "data"


def test_a_missing_capture_says_where_it_looked_and_what_to_set(tmp_path, monkeypatch):
    monkeypatch.setenv("SLWARP_DATA", str(tmp_path))
    with pytest.raises(data.CaptureNotFound) as e:
        data.real_capture_dir("procam_chessboard")
    message = str(e.value)
    assert str(tmp_path / "procam_chessboard") in message and f"SLWARP_DATA={tmp_path}" in message
    assert "docs/real-captures.md" in message and "\n" not in message
    monkeypatch.delenv("SLWARP_DATA")
    monkeypatch.setattr(data, "DEFAULT_DATA", tmp_path / "elsewhere")
    with pytest.raises(OSError, match="set SLWARP_DATA=FOLDER"):  # an OSError: the CLI reports it in one line
        data.real_capture_dir("procam_chessboard")
