"""Atomic writes: an interrupted save leaves the previous file, and files get the usual modes."""

import json
import os
import stat

import pytest

from canrig_jax._io import atomic_path, save_json, save_text


def _mode(path) -> int:
    return stat.S_IMODE(os.stat(path).st_mode)


def test_an_interrupted_save_keeps_the_previous_file_and_leaves_no_temporary(tmp_path):
    path = tmp_path / "results.json"
    save_json(path, {"a": 1})
    with pytest.raises(RuntimeError), atomic_path(path) as tmp:
        tmp.write_text("half a file")
        raise RuntimeError("interrupted")
    assert json.loads(path.read_text()) == {"a": 1}
    assert [p.name for p in tmp_path.iterdir()] == ["results.json"]


def test_new_files_get_the_mode_of_a_plain_open_and_replacements_keep_theirs(tmp_path):
    plain = tmp_path / "plain.txt"
    plain.write_text("x")  # what open() gives under the current umask
    atomic = save_text(tmp_path / "atomic.txt", "x")
    assert _mode(atomic) == _mode(plain)  # not mkstemp's 0o600
    os.chmod(atomic, 0o640)
    save_text(atomic, "y")
    assert _mode(atomic) == 0o640 and atomic.read_text() == "y"
