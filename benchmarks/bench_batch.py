"""Batch throughput: the three commands' batches on 1, 2 and all cores, on local processes, a Dask cluster the
benchmark starts in-process, and a Dask cluster started separately by its two commands (run on demand; prints
figures).

    .venv/bin/python benchmarks/bench_batch.py [--sequences 4] [--commands reconstruct track evaluate] [--repeat 1]
        [--engines local dask separate [ray]] [--data DIR]

Each command runs as a user runs it (a fresh process: its imports and its local processes' start count), on
copies of the bundled sample mug (60 frames): ``reconstruct-sequence`` on SEQUENCES sequences with their true
poses, ``annotate --track`` on SEQUENCES sequences with three placed boxes each (reset before every run), and
``evaluate --method template`` on the first 16 frames of two of them. Printed per engine and worker count: the
wall time of the command, its throughput (sequences, or evaluate's predictions, a minute), the speed-up against one local process, and whether
its outputs are the same files as one local process's (reports' timings aside). Engines: ``local``
(``--workers N``), ``dask`` (a LocalCluster of one worker running N units at once, started before the timing), ``separate``
(``dask scheduler`` and ``dask worker ADDRESS --nthreads N`` started as the README says, before the
timing), ``ray`` (when Ray imports: ``ray start --head --num-cpus N``, and the same units through a Ray task per
unit: how the engine was chosen). The machine is shared: the load average is printed before and after each
command, and --repeat keeps the fastest of several runs.

Goal (issue 48): at least 1.7x with 2 workers against 1 on the 2-core machine, with identical outputs.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import os
import shutil
import socket
import subprocess
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
PY = sys.executable
BIN = REPO / ".venv" / "bin" if (REPO / ".venv" / "bin" / "reconstruct-sequence").exists() else Path(sys.executable).parent  # the commands
RAY = Path(sys.executable).parent / "ray"  # Ray's command, where this Python has Ray
EVAL_FRAMES = 16
GOAL = 1.7


def prepare(data: Path, count: int) -> dict:
    """The benchmark's inputs under ``data`` (made once): truth-posed and box-placed copies of the sample, a dataset."""
    import numpy as np

    from sequences.annotation import Annotation, FramePose, save_annotation
    from sequences.reader import open_sequence
    from sequences.sample import sample_sequence
    from sequences.synth import load_truth

    source = sample_sequence()
    truth, ids = load_truth(source), list(open_sequence(source).ids)
    paths = {"rec": [], "trk": [], "evl": []}
    for kind in paths:
        for i in range(count if kind != "evl" else 2):
            root = data / kind / f"mug_{i}"
            paths[kind].append(root)
            if (root / "annotation.yaml").is_file():
                continue
            keep = ids if kind != "evl" else ids[:EVAL_FRAMES]
            (root / "rgb").mkdir(parents=True, exist_ok=True)
            (root / "depth").mkdir(exist_ok=True)
            for files in open_sequence(source).frames:
                if files.id in keep:
                    shutil.copy2(files.color_path, root / "rgb" / files.color_path.name)
                    shutil.copy2(files.depth_path, root / "depth" / files.depth_path.name)
            document = Annotation(sequence=f"mug_{i}", category="mug", symmetry="none", extents=np.asarray(truth.extents) * (1.04 if kind == "trk" else 1))
            rng = np.random.default_rng(i)
            for position, frame_id in enumerate(keep):
                if kind != "trk":
                    document.frames[frame_id] = FramePose.from_matrix(truth.poses[frame_id], "tracked")
                elif position in (4, 31, 57):  # placed boxes, a few mm off as a person places them
                    T = truth.poses[frame_id].copy()
                    T[:3, 3] += rng.uniform(-0.003, 0.003, 3)
                    document.frames[frame_id] = FramePose.from_matrix(T, "manual")
            save_annotation(document, root / "annotation.yaml", backup=False)
            shutil.copy2(root / "annotation.yaml", root / "placed.yaml")
    dataset = data / "evl_gt"
    if not (dataset / "annotations.json").is_file():
        run([str(BIN / "reconstruct-sequence"), *map(str, paths["evl"]), "--out", str(dataset), "--quiet"])
    paths["dataset"] = dataset
    return paths


def run(argv: list[str], env: dict | None = None) -> float:
    start = time.perf_counter()
    result = subprocess.run(argv, cwd=REPO, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env)
    if result.returncode != 0:
        raise SystemExit(f"{' '.join(argv[:3])} ... failed ({result.returncode}):\n{result.stderr[-2000:]}")
    return time.perf_counter() - start


def digest(paths: list[Path]) -> str:
    """One hash of the given files and folders (recursively; batch bookkeeping and the reports' timings aside)."""
    sha = hashlib.sha256()
    for top in paths:
        files = sorted(p for p in Path(top).rglob("*") if p.is_file()) if Path(top).is_dir() else [Path(top)]
        for path in files:
            rel = path.relative_to(top).as_posix() if Path(top).is_dir() else path.name
            if rel.startswith(".batch/") or rel == ".export.lock":
                continue
            data = path.read_bytes()
            if rel.startswith("reports/") and rel.endswith(".json"):
                report = json.loads(data)
                report.pop("timings", None)
                data = json.dumps(report, sort_keys=True).encode()
            sha.update(rel.encode() + b"\0" + hashlib.sha256(data).digest())
    return sha.hexdigest()[:12]


def command(name: str, paths: dict, out: Path, engine_args: list[str]) -> tuple[list[str], list[Path], int]:
    """The command line, the outputs it writes, and its number of units."""
    if name == "reconstruct":
        return ([str(BIN / "reconstruct-sequence"), *map(str, paths["rec"]), "--out", str(out), "--quiet", *engine_args],
                [out], len(paths["rec"]))
    if name == "track":
        for root in paths["trk"]:  # from the placed boxes every time
            shutil.copy2(root / "placed.yaml", root / "annotation.yaml")
            (root / "annotation.yaml.tracked.json").unlink(missing_ok=True)
        return [str(BIN / "annotate"), "--track", *map(str, paths["trk"]), *engine_args], [r / "annotation.yaml" for r in paths["trk"]], len(paths["trk"])
    frames = str(paths["evl"][0].parent)
    return ([str(BIN / "evaluate"), "--dataset", str(paths["dataset"]), "--frames", frames, "--method", "template", "--out", str(out), "--quiet",
             *engine_args], [out / "results.json", out / "errors.csv"], EVAL_FRAMES * len(paths["evl"]))


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


class Separate:
    """A Dask scheduler and workers started as separate processes by the README's commands."""

    def __init__(self, workers: int) -> None:
        port = free_port()
        self.address = f"tcp://127.0.0.1:{port}"
        start = time.perf_counter()
        self.scheduler = subprocess.Popen([str(BIN / "dask"), "scheduler", "--host", "127.0.0.1", "--port", str(port), "--no-dashboard"],
                                          stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        self.worker = subprocess.Popen([str(BIN / "dask"), "worker", self.address, "--nthreads", str(workers), "--no-dashboard"],
                                       stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        from distributed import Client

        with Client(self.address, timeout="60s") as client:
            client.wait_for_workers(1, timeout=120)
        self.started = time.perf_counter() - start

    def close(self) -> None:
        for process in (self.worker, self.scheduler):
            process.terminate()
            process.wait(30)


def ray_driver() -> None:
    """``bench_batch.py --ray-driver ADDRESS COMMAND ARGS...``: run a command with its units as Ray tasks."""
    address, name, argv = sys.argv[2], sys.argv[3], sys.argv[4:]
    import ray

    import batch.runner
    from batch.local import run_in_process
    from batch.units import error_line

    class RayPool:
        """The engine interface on Ray: a task per unit step, which runs it in a fresh process as Dask's workers do."""

        def __init__(self, preload) -> None:
            ray.init(address=address, log_to_driver=False)
            self.remote = ray.remote(num_cpus=1)(run_in_process)
            self.pending: dict = {}
            self.preload = tuple(preload)

        def describe(self) -> str:
            return f"Ray cluster {address}"

        def __enter__(self):
            return self

        def __exit__(self, *exc) -> None:
            ray.shutdown()

        def submit(self, token, function, args, priority=0) -> None:
            self.pending[self.remote.remote(function, args, self.preload)] = token

        def next_result(self):
            if not self.pending:
                return None
            ready, _ = ray.wait(list(self.pending), num_returns=1)
            token = self.pending.pop(ready[0])
            try:
                return token, ray.get(ready[0])
            except Exception as error:
                return token, {"ok": False, "error": error_line(error), "seconds": 0.0, "worker": None}

    batch.runner.make_engine = lambda workers, cluster, preload=(), inline=False: RayPool(preload)
    if name == "reconstruct":
        from reconstruct.cli import main
    elif name == "track":
        from annotate.cli import main
    else:
        from evaluate.cli import main
    raise SystemExit(main(argv))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--sequences", type=int, default=4, help="sequences per batch (default 4)")
    parser.add_argument("--commands", nargs="+", default=["reconstruct", "track", "evaluate"], choices=["reconstruct", "track", "evaluate"])
    parser.add_argument("--engines", nargs="+", default=["local", "dask", "separate"], choices=["local", "dask", "separate", "ray"])
    parser.add_argument("--repeat", type=int, default=1, help="runs per figure; the fastest is kept (default 1)")
    parser.add_argument("--data", help="folder for the inputs (default: a temporary one)")
    args = parser.parse_args()
    from batch.local import available_cores

    cores = available_cores()
    counts = sorted({1, 2, cores})
    data = Path(args.data) if args.data else Path(tempfile.mkdtemp(prefix="bench_batch_"))
    paths = prepare(data, args.sequences)
    print(f"{cores} cores; {args.sequences} sequences of the 60-frame sample per batch; evaluate: template on {2 * EVAL_FRAMES} samples; "
          f"load {os.getloadavg()[0]:.2f}", flush=True)
    rows, reference, base = [], {}, {}
    for engine in args.engines:
        for workers in counts:
            cluster, started, env = None, 0.0, None
            if engine == "dask":
                from distributed import LocalCluster

                t = time.perf_counter()
                cluster = LocalCluster(n_workers=1, threads_per_worker=workers, processes=True, dashboard_address=None, host="127.0.0.1")
                started, address = time.perf_counter() - t, cluster.scheduler_address
            elif engine == "separate":
                cluster = Separate(workers)
                started, address = cluster.started, cluster.address
            elif engine == "ray":
                t = time.perf_counter()
                env = dict(os.environ, PYTHONPATH=str(REPO))
                subprocess.run([str(RAY), "start", "--head", f"--num-cpus={workers}", "--include-dashboard=false", "--disable-usage-stats"],
                               check=True, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, env=env)
                started, address = time.perf_counter() - t, "auto"
            try:
                for name in args.commands:
                    best, same = None, True
                    for _ in range(args.repeat):
                        out = data / "out" / f"{name}-{engine}-{workers}"
                        shutil.rmtree(out, ignore_errors=True)
                        engine_args = ["--workers", str(workers)] if engine == "local" else [] if engine == "ray" else ["--cluster", address]
                        argv, outputs, units = command(name, paths, out, engine_args)
                        if engine == "ray":
                            argv = [PY, __file__, "--ray-driver", address, name, *argv[1:]]
                        load = os.getloadavg()[0]
                        seconds = run(argv, env)
                        key = digest(outputs)
                        reference.setdefault(name, key)
                        same = same and key == reference[name]
                        best = seconds if best is None else min(best, seconds)
                    if engine == "local" and workers == 1:
                        base[name] = best
                    speedup = base[name] / best if name in base else float("nan")
                    rows.append((name, engine, workers, best, 60 * units / best, speedup, same, started, load))
                    print(f"{name:12s} {engine:9s} {workers:2d} workers: {best:6.1f} s, {60 * units / best:5.1f} units/min, {speedup:4.2f}x, "
                          f"outputs {'identical' if same else 'DIFFER'}; cluster start {started:.1f} s; load before {load:.2f}", flush=True)
            finally:
                if engine == "dask":
                    cluster.close()
                elif engine == "separate":
                    cluster.close()
                elif engine == "ray":
                    subprocess.run([str(RAY), "stop", "--force"], stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    print("\n| command | engine | workers | s | units/min | speed-up vs 1 local | outputs |")
    print("|---|---|---|---|---|---|---|")
    for name, engine, workers, seconds, rate, speedup, same, _, _ in rows:
        print(f"| {name} | {engine} | {workers} | {seconds:.1f} | {rate:.1f} | {speedup:.2f}x | {'identical' if same else 'DIFFER'} |")
    for name in args.commands:
        two = [r for r in rows if r[0] == name and r[1] == "local" and r[2] == 2]
        if two:
            print(f"goal {name}: {two[0][5]:.2f}x with 2 local workers against 1 (goal >= {GOAL}x): {'met' if two[0][5] >= GOAL else 'MISSED'}")
    print(f"load after {os.getloadavg()[0]:.2f}")


if __name__ == "__main__":
    if len(sys.argv) > 1 and sys.argv[1] == "--ray-driver":
        ray_driver()
    else:
        main()
