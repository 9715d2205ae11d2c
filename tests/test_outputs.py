"""OutputFolder, the one writer of every command's results: staged, committed together, nothing lost."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

from perception.logs.outputs import OutputFolder


def _tree(root: Path) -> dict[str, bytes]:
    return {str(p.relative_to(root)): p.read_bytes() for p in root.rglob("*") if p.is_file()}


def test_products_are_staged_with_their_extension_and_committed_together(tmp_path):
    out = tmp_path / "a" / "b"
    with OutputFolder(out, ("r.csv", "plot.png", "run/metrics.json")) as f:
        tmp = f.stage("plot.png")
        assert tmp.parent == out and tmp.name.startswith(".plot.") and tmp.suffix == ".png"
        tmp.write_bytes(b"png")
        f.write_text("r.csv", "x\n")
        f.write_text("run/metrics.json", "{}")
        assert not (out / "r.csv").exists()  # nothing in place before the commit
        f.commit()
    assert _tree(out) == {"r.csv": b"x\n", "plot.png": b"png", "run/metrics.json": b"{}"}


@pytest.mark.parametrize("name", ["", "   "])
def test_an_empty_name_is_refused_not_the_current_folder(tmp_path, monkeypatch, name):
    monkeypatch.chdir(tmp_path)
    with pytest.raises(ValueError, match="--out: empty"):
        OutputFolder(name, ("r.csv",))
    assert not list(tmp_path.iterdir())


def test_a_result_is_never_written_through_a_symbolic_link(tmp_path):
    outside = tmp_path / "elsewhere.csv"
    outside.write_text("the user's file")
    out = tmp_path / "out"
    out.mkdir()
    (out / "r.csv").symlink_to(outside)
    for overwrite in (False, True):
        with pytest.raises(ValueError, match=r"r\.csv is a symbolic link .*never written through a link"):
            OutputFolder(out, ("r.csv",), overwrite=overwrite)
    (tmp_path / "dir").mkdir()
    (out / "run").symlink_to(tmp_path / "dir")  # a folder product's parent
    with pytest.raises(ValueError, match="run is a symbolic link"):
        OutputFolder(out, ("run/metrics.json",))
    assert outside.read_text() == "the user's file" and not list((tmp_path / "dir").iterdir())


def test_a_folder_where_a_file_is_due_is_refused_before_any_work(tmp_path):
    out = tmp_path / "out"
    (out / "plot.png").mkdir(parents=True)
    with pytest.raises(ValueError, match="plot.png is a folder where this tool writes a file"):
        OutputFolder(out, ("r.csv", "plot.png"), overwrite=True)
    (out / "runs").write_text("not a folder")
    with pytest.raises(ValueError, match="runs is a file where this tool writes a folder"):
        OutputFolder(out, ("runs/",), overwrite=True)


def test_a_refused_or_failed_run_leaves_no_folder_and_keeps_the_users_files(tmp_path):
    out = tmp_path / "new" / "run"
    with pytest.raises(RuntimeError), OutputFolder(out, ("r.csv", "run/x.txt")) as f:
        f.write_text("run/x.txt", "half")
        raise RuntimeError("the work failed")
    assert not (tmp_path / "new").exists()  # every folder this run made is gone again
    mine = tmp_path / "mine"
    mine.mkdir()
    (mine / "notes.txt").write_text("keep")
    with pytest.raises(RuntimeError), OutputFolder(mine, ("r.csv",)) as f:
        f.write_text("r.csv", "half")
        raise RuntimeError("the work failed")
    assert _tree(mine) == {"notes.txt": b"keep"}


def test_overwrite_replaces_what_this_run_writes_and_leaves_the_rest(tmp_path, caplog):
    out = tmp_path / "out"
    with OutputFolder(out, ("a.csv", "b.tum")) as f:
        f.write_text("a.csv", "1")
        f.write_text("b.tum", "1")
        f.commit()
    with pytest.raises(ValueError, match=r"earlier run \(a.csv, b.tum\); pass --overwrite"):
        OutputFolder(out, ("a.csv", "b.tum"))
    with OutputFolder(out, ("a.csv", "b.tum"), overwrite=True) as f:
        f.write_text("a.csv", "2")  # this run makes no b.tum
        f.commit()
    assert _tree(out) == {"a.csv": b"2", "b.tum": b"1"}
    assert "b.tum is not from this run" in caplog.text
    with OutputFolder(out, ("a.csv", "b.tum"), keep=True) as f:  # a resumed run adds to it
        f.commit()
    assert _tree(out) == {"a.csv": b"2", "b.tum": b"1"}


def test_a_failed_commit_puts_the_earlier_results_back(tmp_path, monkeypatch):
    out = tmp_path / "out"
    with OutputFolder(out, ("a.csv", "b.csv")) as f:
        f.write_text("a.csv", "old a")
        f.write_text("b.csv", "old b")
        f.commit()
    real = os.replace
    calls = []

    def replace(src, dst):  # the second product cannot be renamed into place
        calls.append(dst)
        if str(dst).endswith("b.csv") and not str(src).endswith(".earlier"):
            raise OSError(28, "No space left on device", str(dst))
        return real(src, dst)

    with OutputFolder(out, ("a.csv", "b.csv"), overwrite=True) as f:
        f.write_text("a.csv", "new a")
        f.write_text("b.csv", "new b")
        monkeypatch.setattr(os, "replace", replace)
        with pytest.raises(OSError, match=r"b\.csv: cannot write .*the folder is as it was"):
            f.commit()
        monkeypatch.setattr(os, "replace", real)
    assert _tree(out) == {"a.csv": b"old a", "b.csv": b"old b"}


def test_a_full_disk_names_the_file_and_keeps_the_earlier_result(tmp_path, monkeypatch):
    if not Path("/dev/full").exists():
        pytest.skip("no /dev/full")
    out = tmp_path / "out"
    with OutputFolder(out, ("a.csv",)) as f:
        f.write_text("a.csv", "old")
        f.commit()
    stage = OutputFolder.stage

    def full(self, name):  # the staged file is a disk with no space left (ENOSPC on write)
        tmp = stage(self, name)
        tmp.unlink()
        tmp.symlink_to("/dev/full")
        return tmp

    monkeypatch.setattr(OutputFolder, "stage", full)
    with pytest.raises(OSError, match=r"a\.csv: cannot write \(No space left"):
        with OutputFolder(out, ("a.csv",), overwrite=True) as f:
            f.write_text("a.csv", "x" * 100_000)
    assert _tree(out) == {"a.csv": b"old"}


def test_folder_products_hold_incremental_work_and_go_only_if_empty(tmp_path):
    out = tmp_path / "out"
    with pytest.raises(RuntimeError), OutputFolder(out, ("report.md", "runs/", "tb/")) as f:
        runs = f.subfolder("runs/")
        f.subfolder("tb/")
        (runs / "run_0").mkdir()
        (runs / "run_0" / "row.json").write_text("{}")  # a finished run: kept through an interruption
        raise RuntimeError("interrupted")
    assert _tree(out) == {"runs/run_0/row.json": b"{}"}  # tb/ was empty: removed
    with pytest.raises(ValueError, match=r"earlier run \(runs/\)"):
        OutputFolder(out, ("report.md", "runs/"))
    with OutputFolder(out, ("report.md", "runs/"), keep=True) as f:
        f.subfolder("runs/")
        f.write_text("report.md", "done")
        f.commit()
    assert _tree(out) == {"runs/run_0/row.json": b"{}", "report.md": b"done"}


def test_the_input_is_never_the_output(tmp_path):
    src = tmp_path / "images"
    src.mkdir()
    with pytest.raises(ValueError, match="holds the input"):
        OutputFolder(tmp_path, ("r.csv",), inputs=(src,))
    with pytest.raises(ValueError, match="not one of this tool's file products"):
        OutputFolder(tmp_path / "o", ("r.csv",)).stage("other.csv")
    with pytest.raises(ValueError, match="relative name"):
        OutputFolder(tmp_path / "o2", ("../escape.csv",))
