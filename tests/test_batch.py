"""Batches (batch/): annotate --track SEQ..., reconstruct-sequence SEQ... and evaluate on local processes and a Dask
cluster. The outputs are the same for 1 and 2 workers and on the cluster, a rerun skips finished units and redoes
changed ones, a failing unit or a killed worker fails alone, ordered commits keep the command line's order, and
--json prints one JSON object on stdout.

The sequences: copies of the bundled sample mug, cut to its first 16 frames (tracking and reconstruction take a
few seconds each)."""

from __future__ import annotations

import json
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from batch import Unit, run_batch
from batch.local import LocalPool
from batch.report import output_files
from sequences.annotation import Annotation, FramePose, load_annotation, save_annotation

REPO = Path(__file__).resolve().parents[1]
FRAMES = 16
MANUAL = (1, 9)  # frames (positions) that carry a placed box in the tracking documents


def _cut_sample(root: Path, name: str, frames: int = FRAMES) -> list[str]:
    """The bundled sample's first ``frames`` frames as ``root``; returns their ids."""
    from sequences.reader import open_sequence
    from sequences.sample import sample_sequence

    source = open_sequence(sample_sequence())
    (root / "rgb").mkdir(parents=True)
    (root / "depth").mkdir()
    for files in source.frames[:frames]:
        shutil.copy2(files.color_path, root / "rgb" / files.color_path.name)
        shutil.copy2(files.depth_path, root / "depth" / files.depth_path.name)
    return [f.id for f in source.frames[:frames]]


def _document(name: str, ids: list[str], all_frames: bool) -> Annotation:
    """The sample's truth as a document: every frame (to reconstruct) or the MANUAL ones placed (to track)."""
    from sequences.sample import sample_sequence
    from sequences.synth import load_truth

    truth = load_truth(sample_sequence())
    annotation = Annotation(sequence=name, category="mug", symmetry="none", extents=np.asarray(truth.extents))
    for i, frame_id in enumerate(ids):
        if all_frames or i in MANUAL:
            annotation.frames[frame_id] = FramePose.from_matrix(truth.poses[frame_id], "manual" if i in MANUAL else "tracked")
    return annotation


@pytest.fixture(scope="module")
def sequences(tmp_path_factory) -> list[Path]:
    """Three copies of the cut sample with the true poses of every frame (mug_a, mug_b, mug_c)."""
    try:
        base = tmp_path_factory.mktemp("batch_seqs")
        roots = []
        for name in ("mug_a", "mug_b", "mug_c"):
            ids = _cut_sample(base / name, name)
            save_annotation(_document(name, ids, True), base / name / "annotation.yaml", backup=False)
            roots.append(base / name)
    except Exception as error:  # the sample is generated on first use
        pytest.skip(f"bundled sample unavailable: {error}")
    return roots


def _copies(roots: list[Path], into: Path) -> list[Path]:
    into.mkdir()
    out = []
    for root in roots:
        shutil.copytree(root, into / root.name)
        out.append(into / root.name)
    return out


def _reconstruct(*args: str) -> int:
    from reconstruct.cli import main

    return main([*args, "--voxel-size", "0.004", "--quiet"])


# ------------------------------------------------------------------------------------------------ reconstruct-sequence

@pytest.mark.slow  # 15-20 s on the 2-core machine
def test_reconstruct_batch_is_the_same_for_1_and_2_workers_and_a_rerun_skips_finished_sequences(sequences, tmp_path, capsys):
    one, two = tmp_path / "one", tmp_path / "two"
    # the order on the command line is not the alphabetical one: annotations.json follows the command line
    order = [str(sequences[2]), str(sequences[0]), str(sequences[1])]
    assert _reconstruct(*order, "--out", str(one), "--workers", "1") == 0
    assert _reconstruct(*order, "--out", str(two), "--workers", "2") == 0
    assert output_files(one) == output_files(two)
    assert list(json.loads((two / "annotations.json").read_text())) == ["mug_c", "mug_a", "mug_b"]
    assert sorted(p.name for p in (two / ".batch").iterdir()) == ["mug_a.json", "mug_b.json", "mug_c.json"]
    capsys.readouterr()
    # a rerun skips all three; a document edited since (a frame's pose moved) runs again, alone
    stamp = (two / "mug_a.obj").stat().st_mtime_ns
    document = load_annotation(sequences[1] / "annotation.yaml")
    edited = _copies([sequences[1]], tmp_path / "edited")[0]
    assert _reconstruct(*order, "--out", str(two), "--json") == 0
    report = json.loads(capsys.readouterr().out)
    assert [u["status"] for u in report["units"]] == ["skipped"] * 3 and report["skipped"] == 3
    assert (two / "mug_a.obj").stat().st_mtime_ns == stamp
    frame = next(iter(document.frames))
    document.frames[frame].position = document.frames[frame].position + 0.001
    save_annotation(document, edited / "annotation.yaml", backup=False)
    assert _reconstruct(str(sequences[2]), str(sequences[0]), str(edited), "--out", str(two), "--json") == 0
    report = json.loads(capsys.readouterr().out)
    assert [u["status"] for u in report["units"]] == ["skipped", "skipped", "done"]
    # --redo runs finished ones again, to the same files
    assert _reconstruct(str(sequences[2]), str(sequences[0]), "--out", str(one), "--redo", "--json") == 0
    assert [u["status"] for u in json.loads(capsys.readouterr().out)["units"]] == ["done", "done"]
    assert output_files(one) == output_files(tmp_path / "one")


def test_reconstruct_batch_bop_numbers_scenes_in_command_line_order_for_any_worker_count(sequences, tmp_path):
    order = [str(sequences[1]), str(sequences[2]), str(sequences[0])]
    assert _reconstruct(*order, "--out", str(tmp_path / "one"), "--format", "bop", "--no-masks", "--workers", "1") == 0
    assert _reconstruct(*order, "--out", str(tmp_path / "two"), "--format", "bop", "--no-masks", "--workers", "2") == 0
    assert output_files(tmp_path / "one") == output_files(tmp_path / "two")
    index = json.loads((tmp_path / "two" / "annotations.json").read_text())
    assert [(name, entry["scene_id"]) for name, entry in index.items()] == [("mug_b", 1), ("mug_c", 2), ("mug_a", 3)]


def test_a_failing_sequence_fails_alone(sequences, tmp_path, capsys):
    broken = _copies([sequences[0]], tmp_path / "bad")[0]
    (broken / "annotation.yaml").write_text("category: mug\nframes: {'0000001': {position: [0, 0, .nan], orientation: [0, 0, 0, 1]}}\n")
    out = tmp_path / "out"
    assert _reconstruct(str(broken), str(sequences[1]), "--out", str(out), "--workers", "2", "--json") == 2
    captured = capsys.readouterr()
    report = json.loads(captured.out)
    assert [u["status"] for u in report["units"]] == ["failed", "done"] and report["failed"] == 1
    assert "NaN" in report["units"][0]["error"] and "bad/mug_a/annotation.yaml" in report["units"][0]["error"]
    errors = [line for line in captured.err.splitlines() if line.startswith("error: ")]
    assert len(errors) == 1 and "NaN" in errors[0]
    assert list(json.loads((out / "annotations.json").read_text())) == ["mug_b"]
    assert not (out / ".batch" / "mug_a.json").exists()


# ------------------------------------------------------------------------------------------------ annotate --track

@pytest.fixture(scope="module")
def to_track(sequences, tmp_path_factory) -> list[Path]:
    """Two of the sequences with two placed boxes each (their documents to be tracked)."""
    base = tmp_path_factory.mktemp("to_track")
    roots = _copies(sequences[:2], base / "seqs")
    for root in roots:
        ids = sorted(load_annotation(root / "annotation.yaml").frames)
        save_annotation(_document(root.name, ids, False), root / "annotation.yaml", backup=False)
    return roots


def test_track_batch_is_the_same_for_1_and_2_workers_and_a_rerun_skips(to_track, tmp_path, capsys):
    from annotate.cli import main

    one, two = _copies(to_track, tmp_path / "one"), _copies(to_track, tmp_path / "two")
    assert main([*map(str, one), "--track", "--workers", "1"]) == 0
    assert main([*map(str, two), "--track", "--workers", "2", "--json"]) == 0
    report = json.loads(capsys.readouterr().out)
    assert [u["status"] for u in report["units"]] == ["done", "done"] and report["units"][0]["frames"] == FRAMES
    for a, b in zip(one, two):
        assert (a / "annotation.yaml").read_bytes() == (b / "annotation.yaml").read_bytes()
        assert (b / "annotation.yaml.tracked.json").is_file()
    tracked = load_annotation(two[0] / "annotation.yaml")
    assert len(tracked.frames) == FRAMES
    # a rerun skips both; a box moved by hand since makes its sequence run again
    assert main([*map(str, two), "--track", "--json"]) == 0
    assert [u["status"] for u in json.loads(capsys.readouterr().out)["units"]] == ["skipped", "skipped"]
    frame = sorted(tracked.frames)[1]
    tracked.frames[frame] = FramePose.from_matrix(tracked.frames[frame].matrix, "manual")
    save_annotation(tracked, two[0] / "annotation.yaml", backup=False)
    assert main([*map(str, two), "--track", "--json"]) == 0
    assert [u["status"] for u in json.loads(capsys.readouterr().out)["units"]] == ["done", "skipped"]
    # one SEQ: tracked here, as ever (no marker, never skipped), the report on stdout with --json
    assert main([str(one[0]), "--track", "--json"]) == 0
    captured = capsys.readouterr()
    report = json.loads(captured.out)
    assert report["engine"] == "this process" and report["units"][0]["frames"] == FRAMES and "tracked 16 frames" in captured.err


def test_track_batch_a_bad_document_fails_alone(to_track, tmp_path, capsys):
    from annotate.cli import main

    good, bad = _copies(to_track, tmp_path / "s")
    (bad / "annotation.yaml").write_text("category: mug\nextents: [0.1, 0.1, 0.1]\nframes: {}\n")
    assert main([str(bad), str(good), "--track", "--workers", "2"]) == 2
    err = capsys.readouterr().err
    errors = [line for line in err.splitlines() if line.startswith("error: ")]
    assert len(errors) == 1 and "no frame has a box" in errors[0] and str(bad) in errors[0]
    assert len(load_annotation(good / "annotation.yaml").frames) == FRAMES


def test_annotate_options_of_batches_apply_to_track_only():
    from annotate.cli import main

    for argv in (["a", "b"], ["a", "--cluster", "tcp://x:1"], ["a", "--json"], ["a", "--redo"], ["a", "b", "--track", "--annotation", "d.yaml"]):
        with pytest.raises(SystemExit) as caught:
            main(argv)
        assert caught.value.code == 2


# ------------------------------------------------------------------------------------------------ evaluate

@pytest.fixture(scope="module")
def dataset(sequences, tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("dataset") / "gt"
    assert _reconstruct(*map(str, sequences), "--out", str(out), "--workers", "2") == 0
    return out


@pytest.mark.slow  # 15-20 s on the 2-core machine
def test_evaluate_chunks_give_the_results_of_one_loop_and_a_rerun_reuses_them(dataset, sequences, tmp_path, capsys, monkeypatch):
    from evaluate.cli import build_parser, main
    from evaluate.config import build_config
    from evaluate.report import write_outputs
    from evaluate.runner import evaluate_dataset

    monkeypatch.setattr("evaluate.units.CHUNK", 7)  # 48 samples: 7 chunks, the last short
    frames = str(sequences[0].parent)
    common = ["--dataset", str(dataset), "--frames", frames, "--method", "box", "--method", "oracle", "--quiet"]
    reference = tmp_path / "loop"
    config = build_config(build_parser().parse_args([*common, "--out", str(reference)]), {})
    evaluation = evaluate_dataset(config, progress=False)  # no batch: the loop of one process
    write_outputs(reference, evaluation.dataset.name, evaluation.results, evaluation.dataset.categories, evaluation.notes)
    for workers in ("1", "2"):
        assert main([*common, "--out", str(tmp_path / workers), "--workers", workers]) == 0
        for name in ("results.json", "errors.csv", "table.md", "curves.json", "nocs_map.csv"):
            assert (tmp_path / workers / name).read_bytes() == (reference / name).read_bytes(), (workers, name)
    assert len(list((tmp_path / "2" / ".batch" / "box").glob("*.npz"))) == 7
    capsys.readouterr()
    assert main([*common, "--out", str(tmp_path / "2"), "--json"]) == 0
    report = json.loads(capsys.readouterr().out)
    assert report["batch"]["skipped"] == 7 and report["batch"]["done"] == 0
    assert report["results"] == json.loads((reference / "results.json").read_text())
    assert (tmp_path / "2" / "results.json").read_bytes() == (reference / "results.json").read_bytes()


def test_evaluate_reruns_the_chunks_whose_truth_or_options_changed(dataset, sequences, tmp_path, capsys, monkeypatch):
    """A chunk's marker covers the truth it was predicted against: a pose edited in annotations.json, a mesh edited
    in place (same size, same time), a predictions file cut, or another seed runs again what they touch, and the
    results are then those of one loop over the edited dataset."""
    from evaluate.cli import build_parser, main
    from evaluate.config import build_config
    from evaluate.runner import evaluate_dataset

    monkeypatch.setattr("evaluate.units.CHUNK", 16)  # 48 samples: one chunk per sequence (mug_a, mug_b, mug_c)
    truth = tmp_path / "gt"
    shutil.copytree(dataset, truth)
    out = tmp_path / "out"
    common = ["--dataset", str(truth), "--frames", str(sequences[0].parent), "--method", "box", "--out", str(out), "--quiet"]

    def statuses(*extra: str) -> list[str]:
        capsys.readouterr()
        assert main([*common, "--workers", "2", "--json", *extra]) == 0
        return [u["status"] for u in json.loads(capsys.readouterr().out)["batch"]["units"]]

    assert statuses() == ["done"] * 3
    assert statuses() == ["skipped"] * 3
    index = json.loads((truth / "annotations.json").read_text())
    assert list(index) == ["mug_a", "mug_b", "mug_c"]
    index["mug_b"]["pose_anns"][3]["position"][0] += 0.01  # the truth of one sample of the second chunk moved by 1 cm
    (truth / "annotations.json").write_text(json.dumps(index, indent=1))
    assert statuses() == ["skipped", "done", "skipped"]
    loop = evaluate_dataset(build_config(build_parser().parse_args(common), {}), progress=False)  # no batch, the edited truth
    results = json.loads((out / "results.json").read_text())["methods"]["box"]
    assert [row["overall"] for row in results["precision"]] == [row.overall for row in loop.results[0].precision]
    mesh = truth / "mug_c.obj"
    info = mesh.stat()
    text = mesh.read_text()
    edited = text.replace("v 0.", "v 1.", 1)  # one vertex moved, the file's size kept
    assert edited != text and len(edited) == len(text)
    mesh.write_text(edited)
    os.utime(mesh, ns=(info.st_atime_ns, info.st_mtime_ns))  # and its time: the content itself must count
    assert statuses() == ["skipped", "skipped", "done"]
    chunk = sorted((out / ".batch" / "box").glob("*.npz"))[0]
    chunk.write_bytes(chunk.read_bytes()[:-10])  # a predictions file cut short
    assert statuses() == ["done", "skipped", "skipped"]
    assert statuses("--seed", "3") == ["done"] * 3  # an option that shapes the predictions
    assert statuses("--seed", "3", "--fscore-threshold", "0.02") == ["skipped"] * 3  # one that only scores them


# ------------------------------------------------------------------------------------------------ the runner

def slow_square(x: int, delay: float) -> dict:
    time.sleep(delay)
    return {"value": x * x}


def slow_pair(x: int, delay: float) -> tuple[dict, int]:
    time.sleep(delay)
    return {"first": x}, x * x


def append_line(value: int, path: str) -> dict:
    with open(path, "a") as handle:
        handle.write(f"{value}\n")
    return {"committed": value}


def die_if(x: int, victim: int) -> dict:
    if x == victim:
        os.kill(os.getpid(), signal.SIGKILL)
    if x == victim + 1:
        raise ValueError("a bug in this unit")
    return {"value": x}


def test_ordered_commits_follow_the_units_order_whatever_finishes_first(tmp_path):
    log = tmp_path / "commits.txt"
    delays = [0.6, 0.0, 0.3, 0.0]  # the later units finish first
    units = [Unit(f"u{i}", slow_pair, (i, d), commit=append_line, commit_args=(str(log),)) for i, d in enumerate(delays)]
    batch = run_batch(units, engine=LocalPool(3), quiet=True)
    assert [o.status for o in batch.outcomes] == ["done"] * 4
    assert log.read_text().split() == ["0", "1", "4", "9"]
    assert batch.outcomes[2].summary == {"first": 2, "committed": 4}


def test_a_killed_worker_and_a_bug_fail_their_units_alone(tmp_path):
    units = [Unit(f"u{i}", die_if, (i, 1)) for i in range(4)]
    batch = run_batch(units, engine=LocalPool(2), quiet=True)
    assert [o.status for o in batch.outcomes] == ["done", "failed", "failed", "done"]
    assert "SIGKILL" in batch.outcomes[1].error and "ValueError: a bug in this unit" == batch.outcomes[2].error


def square_with_state(x: int, state: str | None) -> dict:
    return {"value": x * x} if state is None else {"value": x * x, "state": state}


def test_a_marker_records_the_state_and_another_state_runs_the_unit_again(tmp_path):
    now = {"state": "v1"}

    def unit(returns_state: bool = True) -> Unit:
        return Unit("u", square_with_state, (3, now["state"] if returns_state else None), tmp_path / "u.json", lambda: now["state"])

    assert run_batch([unit()], engine=LocalPool(1), quiet=True).outcomes[0].status == "done"
    record = json.loads((tmp_path / "u.json").read_text())
    assert record["state"] == "v1" and record["summary"] == {"value": 9}
    again = run_batch([unit()], engine=LocalPool(1), quiet=True).outcomes[0]
    assert again.status == "skipped" and again.summary == {"value": 9}
    now["state"] = "v2"
    assert run_batch([unit()], engine=LocalPool(1), quiet=True).outcomes[0].status == "done"
    assert run_batch([unit()], engine=LocalPool(1), quiet=True, redo=True).outcomes[0].status == "done"  # --redo
    (tmp_path / "u.json").unlink()
    run_batch([unit(returns_state=False)], engine=LocalPool(1), quiet=True)  # no state in the summary: no marker
    assert not (tmp_path / "u.json").exists()


def test_the_commands_reach_their_local_processes_start_without_the_heavy_libraries():
    """A batch's local processes start (batch.local.start_server, importing the units' libraries on their own) before
    the command imports anything heavy: the command lines import neither NumPy, SciPy, Open3D, trimesh nor PIL to
    get there, so on two cores the two imports overlap."""
    code = ("import sys, reconstruct.cli, annotate.cli, evaluate.cli, batch.local, batch.report; "
            "print(sorted(m for m in ('numpy', 'scipy', 'open3d', 'trimesh', 'PIL') if m in sys.modules))")
    result = subprocess.run([sys.executable, "-c", code], cwd=REPO, capture_output=True, text=True, timeout=120)
    assert result.returncode == 0, result.stderr[-800:]
    assert result.stdout.strip() == "[]"


def test_the_three_commands_refuse_bad_engine_options_in_the_same_words(tmp_path):
    """--workers 0, and --workers with --cluster: one line on stderr, exit 2, worded alike by annotate --track,
    reconstruct-sequence and evaluate (batch.options), before any work starts."""
    seq = str(tmp_path / "seq")
    commands = {"annotate": [seq, "--track"], "reconstruct": [seq, "--out", str(tmp_path / "out")],
                "evaluate": ["--dataset", str(tmp_path / "gt"), "--method", "template", "--out", str(tmp_path / "res")]}
    for options, wanted in ((["--workers", "0"], "--workers must be at least 1, got 0"),
                            (["--workers", "2", "--cluster", "tcp://127.0.0.1:1"], "--workers and --cluster exclude each other")):
        for name, argv in commands.items():
            code = f"import sys; from {name}.cli import entry; sys.argv = ['{name}', *sys.argv[1:]]; entry()"
            run = subprocess.run([sys.executable, "-c", code, *argv, *options], cwd=REPO, capture_output=True, text=True, timeout=120)
            errors = [line for line in run.stderr.splitlines() if "error:" in line]  # argparse prints its usage above
            assert run.returncode == 2, (name, run.stderr[-500:])
            assert len(errors) == 1 and wanted in errors[0], (name, run.stderr[-500:])


# ------------------------------------------------------------------------------------------------ --json

def test_json_is_the_only_thing_on_stdout(sequences, tmp_path):
    result = subprocess.run([sys.executable, "-c", "import sys; from reconstruct.cli import entry; sys.argv[0] = 'reconstruct-sequence'; entry()",
                             str(sequences[0]), "--out", str(tmp_path / "out"), "--voxel-size", "0.004", "--no-masks", "--json"],
                            cwd=REPO, capture_output=True, text=True, timeout=300)
    assert result.returncode == 0, result.stderr[-800:]
    report = json.loads(result.stdout)  # one object, nothing else
    assert report["units"][0]["sequence"] == "mug_a" and report["units"][0]["status"] == "done"
    assert "1 of 1 sequence(s) written" in result.stderr
    missing = subprocess.run([sys.executable, "-c", "import sys; from reconstruct.cli import entry; sys.argv[0] = 'reconstruct-sequence'; entry()",
                              str(tmp_path / "nothing"), "str", "--out", str(tmp_path / "out"), "--annotation", "x.yaml", "--json"],
                             cwd=REPO, capture_output=True, text=True, timeout=300)
    assert missing.returncode == 2 and "single SEQ" in json.loads(missing.stdout)["error"]
    assert len(missing.stderr.strip().splitlines()) == 1


# ------------------------------------------------------------------------------------------------ a Dask cluster

@pytest.mark.slow  # 15-40 s: a Dask cluster's start, two commands twice
def test_a_local_dask_cluster_gives_the_outputs_of_local_processes(sequences, to_track, tmp_path, capsys):
    from annotate.cli import main as annotate
    from batch.cluster import local_cluster

    local, cluster = _copies(to_track, tmp_path / "local"), _copies(to_track, tmp_path / "cluster")
    assert annotate([*map(str, local), "--track", "--workers", "2"]) == 0
    assert _reconstruct(*map(str, sequences), "--out", str(tmp_path / "out_local"), "--workers", "2") == 0
    with local_cluster(2) as address:
        assert annotate([*map(str, cluster), "--track", "--cluster", address, "--json"]) == 0
        report = json.loads(capsys.readouterr().out)
        assert report["engine"] == f"Dask cluster {address} (2 units at once on 1 worker)"
        assert _reconstruct(*map(str, sequences), "--out", str(tmp_path / "out_cluster"), "--cluster", address) == 0
    for a, b in zip(local, cluster):
        assert (a / "annotation.yaml").read_bytes() == (b / "annotation.yaml").read_bytes()
    assert output_files(tmp_path / "out_local") == output_files(tmp_path / "out_cluster")


def test_an_unreachable_cluster_is_one_line(sequences, tmp_path, monkeypatch):
    from sequences.errors import InputError

    monkeypatch.setattr("batch.cluster.CONNECT_TIMEOUT", "2s")
    with pytest.raises(InputError, match="no Dask scheduler answers"):
        _reconstruct(str(sequences[0]), "--out", str(tmp_path / "o"), "--cluster", "tcp://127.0.0.1:9")
