"""trimeter.paths' safe reads of stored records: real directories and regular files only."""

from __future__ import annotations

import os

import pytest

from trimeter.paths import real_subdirectory, regular_files


def test_real_subdirectory_refuses_links_files_and_odd_names(tmp_path):
    root = tmp_path / "root"
    (root / "a").mkdir(parents=True)
    (root / "f").write_text("x")
    (tmp_path / "elsewhere").mkdir()
    (root / "link").symlink_to(tmp_path / "elsewhere")
    assert real_subdirectory(root, "a") == root / "a"
    for name in ("link", "f", "missing", "..", ".", "", "a/../a", "x" * 256, "a\0"):
        assert real_subdirectory(root, name) is None, name


def test_a_linked_root_is_still_a_root(tmp_path):
    (tmp_path / "real" / "a").mkdir(parents=True)
    (tmp_path / "alias").symlink_to(tmp_path / "real")
    assert real_subdirectory(tmp_path / "alias", "a") == tmp_path / "alias" / "a"


def test_regular_files_lists_neither_links_nor_fifos_nor_directories(tmp_path):
    (tmp_path / "ok").write_bytes(b"12345")
    (tmp_path / "link").symlink_to(tmp_path / "ok")
    os.mkfifo(tmp_path / "fifo")
    (tmp_path / "sub").mkdir()
    assert [p.name for p in regular_files(tmp_path)] == ["ok"]


def test_user_dirs_at_restores_the_environment_also_after_an_error(monkeypatch, tmp_path):
    from trimeter.paths import config_dir, data_dir, user_dirs_at

    monkeypatch.setenv("TRIMETER_DATA_DIR", str(tmp_path / "mine"))
    monkeypatch.delenv("TRIMETER_CONFIG_DIR", raising=False)
    with pytest.raises(RuntimeError), user_dirs_at(data=tmp_path / "demo", config=tmp_path / "cfg"):
        assert data_dir() == tmp_path / "demo" and config_dir() == tmp_path / "cfg"
        raise RuntimeError("mid-demo")
    assert data_dir() == tmp_path / "mine" and "TRIMETER_CONFIG_DIR" not in os.environ
