"""No data lost: posediff replaces or deletes only folders it made itself (``posediff._io``)."""

import os
from pathlib import Path

import pytest

from posediff._io import (
    MARKER,
    OutputFolderError,
    check_output_dir,
    make_output_dir,
    recorded_files,
    remove_own_dir,
    replace_dir,
    seal_output_dir,
)
from posediff.cli import main

BOP_SMALL = ["width=64", "height=48", "pbr_scenes=1", "pbr_images=1", "train_views=1", "test_scenes=1",
             "test_images=1", "progress=false"]  # fmt: skip


def _tree(root: Path) -> dict[str, bytes]:
    return {str(p.relative_to(root)): p.read_bytes() for p in sorted(root.rglob("*")) if p.is_file()}


@pytest.fixture
def work(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Path:
    """``tmp/parent/work`` as the working folder, with a file of the user's in ``parent``."""
    here = tmp_path / "parent" / "work"
    here.mkdir(parents=True)
    (tmp_path / "parent" / "thesis.tex").write_text("years of work")
    (here / "notes.txt").write_text("notes")
    monkeypatch.chdir(here)
    return here


@pytest.mark.parametrize("path", [".", "..", "/", "~", "../.."])
def test_protected_folders_are_refused(work: Path, path: str) -> None:
    with pytest.raises(OutputFolderError, match="give a new folder"):
        check_output_dir(path, "test")
    with pytest.raises(OutputFolderError):
        remove_own_dir(work, "test")  # not marked: never deleted


def test_foreign_folder_is_left_alone(work: Path) -> None:
    foreign = work.parent / "results"
    foreign.mkdir()
    (foreign / "table.csv").write_text("1,2")
    with pytest.raises(OutputFolderError, match="not made by posediff"):
        check_output_dir(foreign, "test")
    with pytest.raises(OutputFolderError, match="not made by posediff"):
        remove_own_dir(foreign, "test")
    partial = make_output_dir(work.parent / "new.partial", "test")
    with pytest.raises(OutputFolderError):
        replace_dir(partial, foreign, "test")
    assert (foreign / "table.csv").read_text() == "1,2" and partial.is_dir()


def test_own_folder_is_replaced(work: Path) -> None:
    old = make_output_dir(work / "out", "test")
    (old / "stale.txt").write_text("old")
    seal_output_dir(old, "test")  # what a finished run records
    new = make_output_dir(work / "out.partial", "test")
    (new / "fresh.txt").write_text("new")
    replace_dir(new, work / "out", "test")
    assert sorted(p.name for p in (work / "out").iterdir()) == [MARKER, "fresh.txt"]
    assert not new.exists() and not list(work.glob(".out.replaced-*"))
    empty = work / "empty"
    empty.mkdir()
    check_output_dir(empty, "test")  # an empty folder loses nothing


def test_a_users_file_in_posediffs_folder_is_never_deleted(work: Path) -> None:
    """overwrite=true used to delete a file a user put into a folder posediff made (the marker covered
    the folder, not the files); now the marker lists what posediff wrote and anything else refuses."""
    old = make_output_dir(work / "out.partial", "test")
    (old / "result.txt").write_text("posediff's")
    replace_dir(old, work / "out", "test")
    assert recorded_files(work / "out") == {"result.txt"}
    (work / "out" / "my_notes.txt").write_text("mine")
    (work / "out" / "mine").mkdir()
    new = make_output_dir(work / "again.partial", "test")
    with pytest.raises(OutputFolderError, match=r"not written by posediff \(mine, my_notes.txt\)"):
        replace_dir(new, work / "out", "test")
    with pytest.raises(OutputFolderError, match="not written by posediff"):
        check_output_dir(work / "out", "test")
    with pytest.raises(OutputFolderError, match="not written by posediff"):
        remove_own_dir(work / "out", "test")
    assert (work / "out" / "my_notes.txt").read_text() == "mine"
    assert (work / "out" / "result.txt").is_file()
    (work / "out" / "my_notes.txt").unlink()
    (work / "out" / "mine").rmdir()
    replace_dir(new, work / "out", "test")  # only posediff's own files left: replaced
    assert not (work / "out" / "result.txt").exists()


def test_paths_under_a_file_and_files(work: Path) -> None:
    with pytest.raises(OutputFolderError, match="is a file, not a folder"):
        check_output_dir(work / "notes.txt" / "out", "test")
    with pytest.raises(OutputFolderError, match="is a file, not a folder"):
        check_output_dir(work / "notes.txt", "test")


@pytest.mark.skipif(os.geteuid() == 0, reason="root writes into read-only folders")
def test_read_only_parent(work: Path) -> None:
    ro = work / "ro"
    ro.mkdir()
    ro.chmod(0o500)
    try:
        with pytest.raises(OutputFolderError, match="permission denied"):
            check_output_dir(ro / "out", "test")
    finally:
        ro.chmod(0o700)


def test_make_bop_overwrite_keeps_foreign_folders(work: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """``make-bop out=.. overwrite=true`` from a sub-folder once wiped the parent; now: one line, nothing touched."""
    before = _tree(work.parent)
    for out in ("..", ".", str(work.parent)):
        assert main(["data", "make-bop", f"out={out}", "overwrite=true", *BOP_SMALL]) == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and "give a new folder" in err[0], err
    assert _tree(work.parent) == before


def test_make_bop_overwrites_its_own_output_only(work: Path, capsys: pytest.CaptureFixture[str]) -> None:
    fx = work / "fx"
    assert main(["data", "make-bop", f"out={fx}", *BOP_SMALL]) == 0
    assert (fx / MARKER).is_file()
    (fx / "mine.txt").write_text("x")  # a user's file in the folder make-bop made: never deleted
    capsys.readouterr()
    assert main(["data", "make-bop", f"out={fx}", "overwrite=true", *BOP_SMALL]) == 2
    assert "holds files not written by posediff (mine.txt)" in capsys.readouterr().err
    assert (fx / "mine.txt").read_text() == "x"
    (fx / "mine.txt").unlink()
    assert main(["data", "make-bop", f"out={fx}", "overwrite=true", *BOP_SMALL]) == 0
    assert (fx / "test_targets_bop19.json").is_file()
    other = work / "data"
    other.mkdir()
    (other / "scans.bin").write_bytes(b"\x00" * 10)
    capsys.readouterr()
    assert main(["data", "make-bop", f"out={other}", "overwrite=true", *BOP_SMALL]) == 2
    assert "not made by posediff" in capsys.readouterr().err
    assert (other / "scans.bin").read_bytes() == b"\x00" * 10 and not (work / "data.partial").exists()


def test_demo_refuses_foreign_out_before_any_work(work: Path, capsys: pytest.CaptureFixture[str]) -> None:
    foreign = work / "mine"
    foreign.mkdir()
    (foreign / "keep.txt").write_text("keep")
    before = _tree(work.parent)
    for out in (str(foreign), "..", "."):
        assert main(["demo", f"out={out}"]) == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and err[0].startswith("posediff demo: "), err
    # a foreign <out>.partial is not deleted either
    (work / "fresh.partial").mkdir()
    (work / "fresh.partial" / "keep.txt").write_text("keep")
    assert main(["demo", "out=fresh"]) == 2
    assert "not made by posediff" in capsys.readouterr().err
    assert _tree(work.parent) == {**before, "work/fresh.partial/keep.txt": b"keep"}
    assert not (work / "data").exists(), "refused before rendering anything"
