"""service/files.py: atomic writes that keep every earlier version (SAFETY.md S8)."""
import os

import pytest

from pointfence.service import files
from pointfence.service.files import backups_of, write_atomic


def leftovers(folder):
    return sorted(p.name for p in folder.iterdir() if p.name.endswith(".tmp"))


def test_new_file_then_two_updates_leave_two_backups(tmp_path):
    f = tmp_path / "scene.toml"
    assert write_atomic(f, "one\n") is None and f.read_text() == "one\n"
    b1 = write_atomic(f, "two\n")
    b2 = write_atomic(f, b"three\n")
    assert (b1.name, b2.name) == ("scene.toml.bak", "scene.toml.bak.2")
    assert (b1.read_text(), b2.read_text(), f.read_text()) == ("one\n", "two\n", "three\n")
    assert backups_of(f) == [b1, b2] and leftovers(tmp_path) == []


def test_an_existing_backup_is_never_overwritten(tmp_path):
    f = tmp_path / "k.toml"
    f.write_text("current")
    (tmp_path / "k.toml.bak").write_text("the user's own backup")
    (tmp_path / "k.toml.bak.7").write_text("an old one")
    b = write_atomic(f, "new")
    assert b.name == "k.toml.bak.8" and b.read_text() == "current"
    assert (tmp_path / "k.toml.bak").read_text() == "the user's own backup"
    assert (tmp_path / "k.toml.bak.7").read_text() == "an old one"
    assert write_atomic(f, "newer", keep_backups=False) is None and len(backups_of(f)) == 3


@pytest.mark.parametrize("where", ["fsync", "replace", "write"])
def test_a_crash_mid_write_leaves_the_original_intact(tmp_path, monkeypatch, where):
    f = tmp_path / "scene.toml"
    f.write_text("original\n")
    os.chmod(f, 0o640)
    write_atomic(f, "first update\n")  # one backup already there
    real_fsync, real_fdopen = os.fsync, os.fdopen
    calls = {"n": 0}

    def crash(*a, **k):
        raise OSError(28, "No space left on device (simulated)")

    def fsync_crash_on_new_content(fd):
        calls["n"] += 1
        if calls["n"] == 2:  # the first fsync is the backup's, the second the new content's
            crash()
        return real_fsync(fd)

    class Dying:
        def __init__(self, f):
            self.f = f

        def __enter__(self):
            return self

        def __exit__(self, *exc):
            self.f.close()

        def write(self, data):
            self.f.write(data[: len(data) // 2])
            crash()

    if where == "fsync":
        monkeypatch.setattr(files.os, "fsync", fsync_crash_on_new_content)
    elif where == "replace":
        monkeypatch.setattr(files.os, "replace", crash)
    else:
        monkeypatch.setattr(files.os, "fdopen", lambda fd, mode: Dying(real_fdopen(fd, mode)))
    with pytest.raises(OSError, match="simulated"):
        write_atomic(f, "second update, never complete\n")
    monkeypatch.undo()
    assert f.read_text() == "first update\n" and oct(os.stat(f).st_mode & 0o777) == oct(0o640)
    assert leftovers(tmp_path) == []
    assert (tmp_path / "scene.toml.bak").read_text() == "original\n"


def test_mode_is_kept_and_a_symlink_is_followed(tmp_path):
    real = tmp_path / "real.key"
    real.write_text("secret")
    os.chmod(real, 0o600)
    link = tmp_path / "link.key"
    link.symlink_to(real)
    b = write_atomic(link, "new secret")
    assert link.is_symlink() and real.read_text() == "new secret"
    assert os.stat(real).st_mode & 0o777 == 0o600 and os.stat(b).st_mode & 0o777 == 0o600
    assert b == tmp_path / "real.key.bak"
    fresh = write_atomic(tmp_path / "fresh.key", "x", mode=0o600)
    assert fresh is None and os.stat(tmp_path / "fresh.key").st_mode & 0o777 == 0o600
