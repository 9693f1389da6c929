"""Nothing a manifest or the output folder can do crashes a batch (issue 12).

Long pair ids are refused up front (exit 2 naming the manifest line); a pair whose outputs cannot be
written becomes that pair's failed row; only a transforms.csv that cannot take even that row stops the
batch (exit 2, finished rows kept).
"""

from __future__ import annotations

import errno
import functools
import os
from pathlib import Path

import pytest
from click.testing import CliRunner
from conftest import read_csv

from data_scripts import fake_engine
from gctr_cli import batch, cli, outdir
from gctr_cli.batch import BatchError, run_batch
from gctr_cli.manifest import MAX_PAIR_ID_BYTES, PairSpec
from gctr_cli.outcome import TRANSFORMS_COLUMNS


@pytest.fixture
def fake_batch(monkeypatch):
    monkeypatch.setattr(batch, "run_batch", functools.partial(batch.run_batch, register_fn=fake_engine.register))


def invoke(*args):
    return CliRunner().invoke(cli.main, [str(a) for a in args], catch_exceptions=False)


def by_id(path):
    return {r["pair_id"]: r for r in read_csv(path)[1]}


def test_a_long_pair_id_is_refused_naming_its_line(four_pairs, tmp_path, fake_batch):
    r = four_pairs.rows[0]  # the case of the issue: the matrix name fits, its temporary name did not
    four_pairs.add_raw("x" * 240, r["source"], r["target"], r["gt"])
    result = invoke("batch", four_pairs.manifest(), "-o", tmp_path / "out", "-q")
    assert result.exit_code == 2
    assert "line 7: pair_id" in result.output and f"is too long (240 bytes in UTF-8, at most {MAX_PAIR_ID_BYTES})" \
        in result.output
    assert not (tmp_path / "out" / "transforms.csv").exists()  # nothing was run


def test_the_longest_allowed_pair_id_runs_end_to_end(dataset, fast_config, tmp_path):
    longest = "é" * (MAX_PAIR_ID_BYTES // 2)  # 200 bytes in UTF-8: every file it names fits in 255
    dataset.add_pair(longest)
    summary = run_batch(dataset.specs(), fast_config, tmp_path / "out", workers=1, register_fn=fake_engine.register,
                        snapshots=True)
    assert summary.n_ok == 1
    assert (tmp_path / "out" / "matrices" / f"{longest}.txt").is_file()
    assert (tmp_path / "out" / "snapshots" / f"{longest}.png").is_file()


def test_pairs_built_in_code_are_checked_too(four_pairs, fast_config, tmp_path):
    spec = four_pairs.specs()[0]
    long = PairSpec(pair_id="y" * 300, source=spec.source, target=spec.target)
    with pytest.raises(BatchError, match="too long"):
        run_batch([spec, long], fast_config, tmp_path / "out", register_fn=fake_engine.register)


def test_outputs_that_cannot_be_written_give_that_pair_a_failed_row(four_pairs, fast_config, tmp_path, fake_batch):
    out = tmp_path / "out"
    (out / "matrices" / "pcd_xyz.txt").mkdir(parents=True)  # the matrix file cannot be created
    result = invoke("batch", four_pairs.manifest(), "-o", out, "-q")
    assert result.exit_code == 1, result.output  # one pair failed, the batch finished
    rows = by_id(out / "transforms.csv")
    assert len(rows) == 5 and sum(r["status"] == "ok" for r in rows.values()) == 4
    bad = rows["pcd_xyz"]
    assert bad["status"] == "failed" and bad["m00"] == ""
    assert bad["message"] == f"cannot write its outputs: {out}/matrices/pcd_xyz.txt: cannot write file (it is a folder)"
    assert bad["fitness"] == "0.875" and float(bad["confidence"]) > 0.5  # what the engine said is kept
    assert "pcd_xyz" not in by_id(out / "tm_errors.csv")  # no error row for a failed pair
    assert "pcd_xyz: cannot write its outputs" in result.output
    # --resume runs that pair again (the folder's fault, not the pair's): still unwritable, failed again
    again = invoke("batch", four_pairs.manifest(), "-o", out, "-q", "--resume")
    assert again.exit_code == 1 and "(4 done by an earlier run)" in again.output
    assert by_id(out / "transforms.csv")["pcd_xyz"]["message"] == bad["message"]
    # once the problem is fixed, --resume completes it
    (out / "matrices" / "pcd_xyz.txt").rmdir()
    fixed = invoke("batch", four_pairs.manifest(), "-o", out, "-q", "--resume")
    assert fixed.exit_code == 0, fixed.output
    rows = by_id(out / "transforms.csv")
    assert len(rows) == 5 and all(r["status"] == "ok" for r in rows.values())
    assert len(read_csv(out / "transforms.csv")[1]) == 5 and "pcd_xyz" in by_id(out / "tm_errors.csv")


def test_a_failed_commit_is_undone_before_the_failed_row(four_pairs, fast_config, tmp_path, monkeypatch):
    """ENOSPC on the commit row: the pair's error row and matrix are removed, then its failed row fits."""
    real_append = outdir.RowLog.append
    failures = []

    def append(self, fields):
        fields = list(fields)
        if self.path.name == "transforms.csv" and fields[0] == "ply_ply" and fields[3] == "ok" and not failures:
            failures.append(fields[0])
            raise OSError(errno.ENOSPC, "No space left on device")
        return real_append(self, fields)

    monkeypatch.setattr(outdir.RowLog, "append", append)
    out = tmp_path / "out"
    summary = run_batch(four_pairs.specs(), fast_config, out, workers=1, register_fn=fake_engine.register)
    assert failures == ["ply_ply"] and summary.n_failed == 1 and summary.n_ok == 4
    row = by_id(out / "transforms.csv")["ply_ply"]
    assert row["status"] == "failed" and "No space left on device" in row["message"]
    assert "ply_ply" not in by_id(out / "tm_errors.csv")
    assert not (out / "matrices" / "ply_ply.txt").exists()
    assert len(read_csv(out / "tm_errors.csv")[1]) == 3  # the other pairs with ground truth


def test_a_transforms_csv_that_takes_no_row_stops_the_batch(four_pairs, fast_config, tmp_path, monkeypatch):
    real_append = outdir.RowLog.append

    def append(self, fields):
        fields = list(fields)
        if self.path.name == "transforms.csv" and fields[0] == "xyz_ply":
            raise OSError(errno.EIO, "Input/output error")
        return real_append(self, fields)

    monkeypatch.setattr(outdir.RowLog, "append", append)
    out = tmp_path / "out"
    with pytest.raises(BatchError, match=r"cannot record pair 'xyz_ply'.*rerun with --resume"):
        run_batch(four_pairs.specs(), fast_config, out, workers=1, register_fn=fake_engine.register)
    rows = by_id(out / "transforms.csv")
    assert "xyz_ply" not in rows and all(r["status"] == "ok" for r in rows.values())
    assert not (out / ".gctr.lock").exists()


def test_resuming_a_folder_without_the_confidence_column_says_why(four_pairs, fast_config, tmp_path):
    out = tmp_path / "out"
    run_batch(four_pairs.specs(), fast_config, out, workers=1, register_fn=fake_engine.register)
    old = [c for c in TRANSFORMS_COLUMNS if c != "confidence"]
    text = (out / "transforms.csv").read_text().splitlines()
    (out / "transforms.csv").write_text(",".join(old) + "\n" + text[1] + "\n")  # as an earlier gctr wrote it
    with pytest.raises(BatchError, match="earlier gctr \\(no confidence column\\)"):
        run_batch(four_pairs.specs(), fast_config, out, resume=True, register_fn=fake_engine.register)


def test_resuming_a_folder_whose_transforms_csv_was_damaged_says_which_line(four_pairs, fast_config, tmp_path):
    """A complete but malformed line (edited by hand, two files concatenated) is an error naming it,
    not a KeyError; the folder is left as it was."""
    out = tmp_path / "out"
    run_batch(four_pairs.specs()[:2], fast_config, out, workers=1, register_fn=fake_engine.register)
    damaged = (out / "transforms.csv").read_text() + "garbage,line\n"
    (out / "transforms.csv").write_text(damaged)
    with pytest.raises(BatchError, match=r"transforms\.csv: line 4 has 2 cells, expected \d+: the file was changed"):
        run_batch(four_pairs.specs(), fast_config, out, resume=True, register_fn=fake_engine.register)
    assert (out / "transforms.csv").read_text() == damaged and not (out / ".gctr.lock").exists()


def test_a_batch_never_overwrites_its_own_inputs(four_pairs, fast_config, tmp_path):
    """Ground truth kept in OUTDIR/matrices/<pair_id>.txt, a manifest named tm_errors.csv in OUTDIR:
    refused before anything runs (exit 2), the files untouched."""
    out = tmp_path / "out"
    (out / "matrices").mkdir(parents=True)
    specs = four_pairs.specs()
    gt = out / "matrices" / f"{specs[1].pair_id}.txt"
    gt.write_text("1 0 0 0\n0 1 0 0\n0 0 1 0\n0 0 0 1\n")
    specs[0] = PairSpec(specs[0].pair_id, specs[0].source, specs[0].target, gt)  # another pair's matrix name
    with pytest.raises(BatchError, match=rf"{gt}: pair '{specs[0].pair_id}' reads it as its ground truth, but the "
                                         rf"batch writes matrices/{specs[1].pair_id}\.txt"):
        run_batch(specs, fast_config, out, workers=1, register_fn=fake_engine.register)
    assert gt.read_text().startswith("1 0 0 0") and not (out / "transforms.csv").exists()

    # aligned/: only the exact file a pair would write (its source's format), not a name it contains
    src = specs[2].source
    aligned = out / "aligned" / f"{specs[2].pair_id}{src.suffix}"
    near = [PairSpec(specs[2].pair_id, src, specs[2].target, aligned.with_name(aligned.name[:-1]))]
    batch.check_inputs_not_overwritten(near, out, snapshots=False, write_aligned=True)
    with pytest.raises(BatchError, match=rf"the batch writes aligned/{aligned.name} \(the aligned cloud"):
        batch.check_inputs_not_overwritten([PairSpec(specs[2].pair_id, src, specs[2].target, aligned)], out,
                                           snapshots=False, write_aligned=True)

    manifest = out / "tm_errors.csv"
    manifest.write_bytes(four_pairs.manifest().read_bytes())
    result = CliRunner().invoke(cli.main, ["batch", str(manifest), "-o", str(out), "-q"])
    assert result.exit_code == 2 and "it is the manifest, but the batch writes tm_errors.csv there" in result.output


@pytest.mark.parametrize("existed", [False, True])
def test_a_full_disk_while_setting_up_leaves_the_folder_as_it_was(four_pairs, fast_config, tmp_path, monkeypatch,
                                                                  existed):
    def no_space(*args, **kwargs):
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(batch, "atomic_write", no_space)  # config.yaml, the first file a run writes
    out = tmp_path / "out"
    if existed:
        out.mkdir()
        (out / "notes.txt").write_text("mine")
    with pytest.raises(BatchError, match=rf"cannot set up output folder {out}: No space left on device; nothing "
                                         "was run"):
        run_batch(four_pairs.specs(), fast_config, out, workers=1, register_fn=fake_engine.register)
    if existed:
        assert sorted(p.name for p in out.iterdir()) == ["notes.txt"]
    else:
        assert not out.exists()
    result = invoke("batch", four_pairs.manifest(), "-o", out, "-q")  # the CLI: exit 2, one line
    assert result.exit_code == 2 and "gctr: error: cannot set up output folder" in result.output
    assert "Traceback" not in result.output


def test_a_stop_right_after_the_first_row_keeps_that_pair(four_pairs, fast_config, tmp_path, monkeypatch):
    """Ctrl-C landing after the first transforms.csv row is written (before the runner counts it): the
    pair is recorded, so nothing is undone."""
    real_append = outdir.RowLog.append

    def append(self, fields):
        fields = list(fields)
        real_append(self, fields)
        if self.path.name == "transforms.csv" and fields[0] != "pair_id":
            raise KeyboardInterrupt

    monkeypatch.setattr(outdir.RowLog, "append", append)
    out = tmp_path / "out"
    with pytest.raises(KeyboardInterrupt):
        run_batch(four_pairs.specs(), fast_config, out, workers=1, register_fn=fake_engine.register)
    rows = by_id(out / "transforms.csv")
    assert len(rows) == 1
    (pair_id,) = rows
    assert (out / "matrices" / f"{pair_id}.txt").is_file() and (out / "config.yaml").is_file()


def test_a_resume_stopped_before_its_first_pair_keeps_the_rows_it_would_rerun(four_pairs, fast_config, tmp_path,
                                                                              monkeypatch):
    out = tmp_path / "out"
    (out / "matrices" / "pcd_xyz.txt").mkdir(parents=True)  # that pair's outputs cannot be written
    run_batch(four_pairs.specs(), fast_config, out, workers=1, register_fn=fake_engine.register)
    before = (out / "transforms.csv").read_bytes()
    assert b"cannot write its outputs" in before

    def interrupted(*args, **kwargs):
        raise KeyboardInterrupt

    monkeypatch.setattr(batch, "outcomes", interrupted)
    with pytest.raises(KeyboardInterrupt):
        run_batch(four_pairs.specs(), fast_config, out, workers=1, register_fn=fake_engine.register, resume=True)
    assert (out / "transforms.csv").read_bytes() == before


def test_a_setup_error_names_the_file(four_pairs, fast_config, tmp_path, monkeypatch):
    """A read-only transforms.csv under --resume said only "Permission denied" (found by an audit)."""
    def refused(path, *args, **kwargs):
        raise PermissionError(errno.EACCES, "Permission denied", str(path))

    monkeypatch.setattr(batch, "atomic_write", refused)
    out = tmp_path / "out"
    with pytest.raises(BatchError, match=rf"cannot set up output folder {out}: {out}/config.yaml: Permission denied; "
                                         "nothing was run"):
        run_batch(four_pairs.specs(), fast_config, out, workers=1, register_fn=fake_engine.register)


def test_a_setup_error_names_the_file_being_written_not_its_temporary_copy(four_pairs, fast_config, tmp_path):
    """A folder where config.yaml goes: the message named the temporary .config.yaml.<pid>.<hex>.tmp, which no
    longer exists when it is read (found in review)."""
    out = tmp_path / "out"
    (out / "config.yaml").mkdir(parents=True)
    with pytest.raises(BatchError, match=rf"cannot set up output folder {out}: {out}/config.yaml: Is a directory; "
                                         "nothing was run"):
        run_batch(four_pairs.specs(), fast_config, out, workers=1, register_fn=fake_engine.register)


def test_a_full_disk_for_the_lock_is_a_setup_error_and_leaves_nothing(four_pairs, fast_config, tmp_path, monkeypatch):
    from gctr_cli import lock

    real_write = lock.os.write

    def write(fd, data):
        if os.readlink(f"/proc/self/fd/{fd}").endswith(".gctr.lock"):
            raise OSError(errno.ENOSPC, "No space left on device")
        return real_write(fd, data)

    monkeypatch.setattr(lock.os, "write", write)
    out = tmp_path / "new" / "deeper" / "out"
    with pytest.raises(BatchError, match=r"cannot set up output folder .*: No space left on device; nothing was run"):
        run_batch(four_pairs.specs(), fast_config, out, workers=1, register_fn=fake_engine.register)
    assert not (tmp_path / "new").exists()  # every folder the run created is gone again


def test_a_stop_before_the_first_pair_removes_only_what_the_run_created(four_pairs, fast_config, tmp_path,
                                                                        monkeypatch):
    """A folder reached through '..' after a folder the run creates, a file someone adds meanwhile, and the
    matrix of a first pair interrupted while it was being recorded. The folder holds an earlier run that
    stopped before its first pair (a header-only ``transforms.csv`` and its ``config.yaml``), the one case
    in which a batch without ``--resume`` may rewrite a ``config.yaml`` it finds: it is put back."""
    (tmp_path / "results").mkdir()
    (tmp_path / "results" / "config.yaml").write_text("the earlier run's\n")
    (tmp_path / "results" / "transforms.csv").write_text(",".join(TRANSFORMS_COLUMNS) + "\n")
    real_append = outdir.RowLog.append

    def append(self, fields):
        fields = list(fields)
        if self.path.name == "transforms.csv" and fields[0] != "pair_id":
            (tmp_path / "results" / "notes.txt").write_text("added while the batch ran")
            raise KeyboardInterrupt  # the matrix is written, the row is not
        return real_append(self, fields)

    monkeypatch.setattr(outdir.RowLog, "append", append)
    monkeypatch.chdir(tmp_path)
    with pytest.raises(KeyboardInterrupt):
        run_batch(four_pairs.specs(), fast_config, "new/../results", workers=1, register_fn=fake_engine.register)
    assert sorted(p.name for p in (tmp_path / "results").iterdir()) == ["config.yaml", "notes.txt", "transforms.csv"]
    assert (tmp_path / "results" / "config.yaml").read_text() == "the earlier run's\n"
    assert read_csv(tmp_path / "results" / "transforms.csv")[1] == []
    assert not (tmp_path / "new").exists()  # created on the way to results/, removed again


def test_a_stop_before_the_first_pair_keeps_an_empty_folder_that_existed(four_pairs, fast_config, tmp_path,
                                                                          monkeypatch):
    """new/../results/sub: the run creates new/ and results/sub/, and removes both; the empty results/ it
    found is kept (the path as written passes through new/, which did not exist, on its way to it)."""
    (tmp_path / "results").mkdir()

    def stop(*args, **kwargs):
        raise KeyboardInterrupt

    monkeypatch.setattr(outdir.RowLog, "append", stop)
    monkeypatch.chdir(tmp_path)
    with pytest.raises(KeyboardInterrupt):
        run_batch(four_pairs.specs(), fast_config, "new/../results/sub", workers=1, register_fn=fake_engine.register)
    assert not (tmp_path / "new").exists()
    assert (tmp_path / "results").is_dir() and list((tmp_path / "results").iterdir()) == []


def test_a_finished_run_keeps_the_folders_on_the_path_it_was_given(four_pairs, fast_config, tmp_path, monkeypatch):
    """new/../results: after a run that recorded pairs the path as given still leads to the results
    (the summary prints it), so the empty new/ it created stays."""
    monkeypatch.chdir(tmp_path)
    run_batch(four_pairs.specs(), fast_config, "new/../results", workers=1, register_fn=fake_engine.register)
    assert (tmp_path / "new").is_dir() and os.path.isfile("new/../results/transforms.csv")
    # a run refused before it ran anything removes what it created on the way, results or not
    other = fast_config.model_copy(update={"seed": fast_config.seed + 1})
    with pytest.raises(BatchError, match="cannot resume: the config differs"):
        run_batch(four_pairs.specs(), other, "new2/../results", resume=True, workers=1,
                  register_fn=fake_engine.register)
    assert not (tmp_path / "new2").exists() and (tmp_path / "results" / "transforms.csv").is_file()


def test_resume_without_the_config_of_the_rows_is_refused(four_pairs, fast_config, tmp_path):
    """config.yaml deleted: --resume took any config and rewrote config.yaml beside rows made with another."""
    out = tmp_path / "out"
    run_batch(four_pairs.specs(), fast_config, out, workers=1, register_fn=fake_engine.register)
    (out / "config.yaml").unlink()
    other = fast_config.model_copy(update={"seed": fast_config.seed + 1})
    with pytest.raises(BatchError, match=r"cannot resume: .*config.yaml, the config the rows of .* is missing"):
        run_batch(four_pairs.specs(), other, out, resume=True, workers=1, register_fn=fake_engine.register)
    assert not (out / "config.yaml").exists()


def test_an_output_folder_name_the_system_refuses_is_exit_2(four_pairs, tmp_path, fake_batch):
    result = invoke("batch", four_pairs.manifest(), "-o", tmp_path / ("a" * 300) / "out", "-q")
    assert result.exit_code == 2 and "cannot create output folder" in result.output
    assert "File name too long" in result.output


@pytest.mark.parametrize("insensitive", [True, False])
def test_pair_ids_that_differ_only_in_case_are_refused_where_their_files_would_collide(
        four_pairs, fast_config, tmp_path, monkeypatch, insensitive):
    """``A`` and ``a`` are two pairs on Linux, but one file on macOS, Windows and many network shares: the
    second matrix would overwrite the first. Refused (nothing run) only where the folder's filesystem does
    not tell them apart."""
    four_pairs.rows = [dict(four_pairs.rows[0], pair_id="Scan_1"), dict(four_pairs.rows[1], pair_id="scan_1")]
    probed = []
    monkeypatch.setattr(outdir, "case_insensitive", lambda folder: probed.append(folder) or insensitive)
    out = tmp_path / "out"
    if insensitive:
        with pytest.raises(BatchError, match=r"pair ids 'Scan_1' and 'scan_1' differ only in case, and the "
                                             r"filesystem of .*out does not tell such file names apart"):
            run_batch(four_pairs.specs(), fast_config, out, workers=1, register_fn=fake_engine.register)
        assert not out.exists()
    else:
        run_batch(four_pairs.specs(), fast_config, out, workers=1, register_fn=fake_engine.register)
        assert sorted(p.name for p in (out / "matrices").iterdir()) == ["Scan_1.txt", "scan_1.txt"]
    assert probed == [out]


def test_the_case_probe_tells_this_filesystem_and_leaves_nothing(tmp_path):
    expected = os.path.exists(str(tmp_path).swapcase()) if str(tmp_path).swapcase() != str(tmp_path) else None
    found = outdir.case_insensitive(tmp_path)
    assert isinstance(found, bool) and list(tmp_path.iterdir()) == []
    if expected is not None:  # the folder's own name, looked up with its case swapped, says the same
        assert found == expected


def test_transforms_csv_is_created_before_config_yaml(four_pairs, fast_config, tmp_path, monkeypatch):
    """A kill -9 between the two must leave a folder the next run accepts: OUTDIR with a config.yaml but no
    transforms.csv is refused as someone else's (``prepare_outdir``), so transforms.csv comes first."""
    real_write = batch.atomic_write
    seen = []

    def atomic_write(path, *args, **kwargs):
        if Path(path).name == "config.yaml":
            seen.append((Path(path).parent / "transforms.csv").is_file())
        return real_write(path, *args, **kwargs)

    monkeypatch.setattr(batch, "atomic_write", atomic_write)
    run_batch(four_pairs.specs(), fast_config, tmp_path / "out", workers=1, register_fn=fake_engine.register)
    assert seen == [True]


def test_a_refused_folder_is_named_as_given(four_pairs, fast_config, tmp_path):
    """OUTDIR reached through a link: the message names the file under the path the user gave."""
    (tmp_path / "real").mkdir()
    (tmp_path / "real" / "report.html").write_text("mine\n")
    (tmp_path / "link").symlink_to(tmp_path / "real")
    with pytest.raises(BatchError) as ei:
        run_batch(four_pairs.specs(), fast_config, tmp_path / "link", workers=1, register_fn=fake_engine.register)
    assert str(ei.value).startswith(f"{tmp_path / 'link' / 'report.html'} already exists, but {tmp_path / 'link'} "
                                    "holds no gctr run")
