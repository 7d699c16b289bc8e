"""Batch throughput: the three commands' batches on 1, 2 and all cores, on local processes, a Dask cluster the
benchmark starts in-process, and a Dask cluster started separately by its two commands (run on demand; prints
figures).

    .venv/bin/python benchmarks/bench_batch.py [--sequences 6] [--commands reconstruct [reconstruct-bop] track evaluate]
        [--repeat 1] [--engines local dask separate [ray]] [--data DIR] [--quiet-below CORES [--wait S]]

Each command runs as a user runs it (a fresh process: its imports and its local processes' start count), on
copies of the bundled sample mug (60 frames): ``reconstruct-sequence`` on SEQUENCES sequences with their true
poses, ``annotate --track`` on SEQUENCES sequences with three placed boxes each (reset before every run), and
``evaluate --method template`` on the first 16 frames of a third of them (at least two). Printed per engine and worker count: the
wall time of the command, its throughput (sequences, or evaluate's predictions, a minute), the speed-up against one local process (one worker of the same engine where local was not run), and whether
its outputs are the same files as one local process's (reports' timings aside). Engines: ``local``
(``--workers N``), ``dask`` (a LocalCluster of one worker running N units at once, started before the timing), ``separate``
(``dask scheduler`` and ``dask worker ADDRESS --nthreads N`` started as the README says, before the
timing), ``ray`` (when Ray imports: ``ray start --head --num-cpus N``, and the same units through a Ray task per
unit: how the engine was chosen). The machine is shared: before each command the load average and the cores other work
keeps busy then (/proc/stat over a second) are printed, --quiet-below waits for a quieter moment, and --repeat
keeps the fastest of several runs, interleaved (a command's worker counts back to back, 1, 2 then 2, 1). Beside
the wall time, from the reports (--json): the CPU seconds of the units and of the command's own process, and from them the wall time on an idle machine (the
client's CPU, then the units' dealt in order to the worker free first; the local processes' server start, 2-3 s
once, left out): on a machine other work keeps busy, what the wall time cannot show.

Goal (issue 48): at least 1.7x with 2 workers against 1 on the 2-core machine, with identical outputs.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import os
import resource
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
COMMANDS = ("reconstruct", "reconstruct-bop", "track", "evaluate")


def eval_sequences(count: int) -> int:
    """Sequences whose first EVAL_FRAMES frames ``evaluate`` reads in a batch of ``count`` sequences: a third of
    them, at least 2 (so a unit of EVAL_FRAMES samples per worker of two, at the least)."""
    return max(2, count // 3)


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
        for i in range(count if kind != "evl" else eval_sequences(count)):
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
    dataset = data / f"evl_gt_{len(paths['evl'])}"
    if not (dataset / "annotations.json").is_file():
        run([str(BIN / "reconstruct-sequence"), *map(str, paths["evl"]), "--out", str(dataset), "--quiet"])
    paths["dataset"] = dataset
    return paths


def run(argv: list[str], env: dict | None = None) -> tuple[float, float, list[float], bool]:
    """Run a command with --json: (wall s, its own process's CPU s, its units' CPU s in order, whether they ran in it)."""
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    start = time.perf_counter()
    result = subprocess.run([*argv, "--json"], cwd=REPO, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env)
    wall = time.perf_counter() - start
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    if result.returncode != 0:
        raise SystemExit(f"{' '.join(argv[:3])} ... failed ({result.returncode}):\n{result.stderr[-2000:]}")
    report = json.loads(result.stdout)
    batch = report.get("batch", report)
    return (wall, (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime), [u["cpu_seconds"] for u in batch["units"]],
            batch["engine"] == "this process")


def busy_cores(seconds: float = 1.0) -> float:
    """The cores other work keeps busy now: from /proc/stat's counters over ``seconds`` (nothing of ours runs then);
    NaN where there is no /proc/stat."""
    def sample() -> tuple[int, int]:
        fields = [int(v) for v in Path("/proc/stat").read_text().split("\n", 1)[0].split()[1:]]
        return sum(fields), fields[3] + fields[4]  # all, idle + iowait (jiffies, every core)

    try:
        total0, idle0 = sample()
        time.sleep(seconds)
        total1, idle1 = sample()
    except OSError:
        return float("nan")
    cores = os.cpu_count() or 1
    return cores * (1.0 - (idle1 - idle0) / max(total1 - total0, 1))


def wait_for_quiet(below: float | None, limit: float) -> float:
    """Wait (at most ``limit`` s) until other work keeps fewer than ``below`` cores busy; returns the busy cores
    measured last (the machine's state when the run starts)."""
    start = time.perf_counter()
    busy = busy_cores()
    while below is not None and busy >= below and time.perf_counter() - start < limit:
        busy = busy_cores(2.0)
    return busy


def idle_estimate(client_cpu: float, unit_cpu: list[float], workers: int, inline: bool) -> float:
    """The wall time on an idle machine from CPU times: the client's, then the units dealt in order to the worker
    free first (as the engines do). Left out: the local processes' server start (2-3 s of imports, once)."""
    if inline:
        return client_cpu
    free = [0.0] * workers
    for cpu in unit_cpu:
        free[free.index(min(free))] += cpu
    return client_cpu + max(free)


def digest(paths: list[Path]) -> str:
    """One hash of the given files and folders (recursively; batch bookkeeping and the reports' timings aside)."""
    from batch.report import output_files

    sha = hashlib.sha256()
    for top in paths:
        for rel, data in output_files(top).items():
            sha.update(rel.encode() + b"\0" + hashlib.sha256(data).digest())
    return sha.hexdigest()[:12]


def command(name: str, paths: dict, out: Path, engine_args: list[str]) -> tuple[list[str], list[Path], int]:
    """The command line, the outputs it writes, and its number of units."""
    if name in ("reconstruct", "reconstruct-bop"):
        fmt = ["--format", "bop"] if name == "reconstruct-bop" else []
        return ([str(BIN / "reconstruct-sequence"), *map(str, paths["rec"]), "--out", str(out), "--quiet", *fmt, *engine_args],
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


class Started:
    """An engine started for the timing (Dask in-process, Ray's head), and how long its start took."""

    def __init__(self, started: float, close) -> None:
        self.started, self.close = started, close


def start_engine(engine: str, workers: int):
    """(the started cluster or None, its address, the environment for the command)."""
    if engine == "dask":
        from distributed import LocalCluster

        t = time.perf_counter()
        cluster = LocalCluster(n_workers=1, threads_per_worker=workers, processes=True, dashboard_address=None, host="127.0.0.1")
        return Started(time.perf_counter() - t, cluster.close), cluster.scheduler_address, None
    if engine == "separate":
        cluster = Separate(workers)
        return cluster, cluster.address, None
    if engine == "ray":
        t = time.perf_counter()
        env = dict(os.environ, PYTHONPATH=str(REPO))
        subprocess.run([str(RAY), "start", "--head", f"--num-cpus={workers}", "--include-dashboard=false", "--disable-usage-stats"],
                       check=True, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, env=env)
        stop = lambda: subprocess.run([str(RAY), "stop", "--force"], stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)  # noqa: E731
        return Started(time.perf_counter() - t, stop), "auto", env
    return None, None, None


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
    if name in ("reconstruct", "reconstruct-bop"):
        from reconstruct.cli import main
    elif name == "track":
        from annotate.cli import main
    else:
        from evaluate.cli import main
    raise SystemExit(main(argv))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--sequences", type=int, default=6, help="sequences per batch (default 6: three per worker of two)")
    parser.add_argument("--commands", nargs="+", default=["reconstruct", "track", "evaluate"], choices=COMMANDS,
                        help="reconstruct-bop: reconstruct-sequence --format bop (its exports render before OUT's lock)")
    parser.add_argument("--engines", nargs="+", default=["local", "dask", "separate"], choices=["local", "dask", "separate", "ray"])
    parser.add_argument("--repeat", type=int, default=1, help="runs per figure, interleaved; the fastest is kept (default 1)")
    parser.add_argument("--data", help="folder for the inputs (default: a temporary one)")
    parser.add_argument("--quiet-below", type=float, default=None, metavar="CORES",
                        help="before each run, wait until other work keeps fewer than CORES cores busy (default: do not wait)")
    parser.add_argument("--wait", type=float, default=300.0, help="the longest such wait, s (default 300; then it runs anyway)")
    parser.add_argument("--bytecode-cache", action="store_true",
                        help="run the commands with compiled modules kept (under DATA/pycache), as a pip installation does; where "
                             "PYTHONDONTWRITEBYTECODE is set, every process otherwise compiles the package's modules again")
    args = parser.parse_args()
    from batch.local import available_cores

    cores = available_cores()
    counts = sorted({1, 2, cores})
    data = Path(args.data) if args.data else Path(tempfile.mkdtemp(prefix="bench_batch_"))
    paths = prepare(data, args.sequences)
    print(f"{cores} cores; {args.sequences} sequences of the 60-frame sample per batch; evaluate: template on {EVAL_FRAMES * eval_sequences(args.sequences)} samples; "
          f"load {os.getloadavg()[0]:.2f}; compiled modules {'kept in DATA/pycache' if args.bytecode_cache else 'as the environment says'} "
          f"(PYTHONDONTWRITEBYTECODE={os.environ.get('PYTHONDONTWRITEBYTECODE', '')!r})", flush=True)
    times: dict[tuple, list[float]] = {}  # (command, engine, workers) -> wall times
    loads: dict[tuple, list[float]] = {}
    busy: dict[tuple, list[float]] = {}
    starts: dict[tuple, float] = {}
    reference: dict[str, str] = {}
    same: dict[tuple, bool] = {}
    units: dict[str, int] = {}  # per command
    estimates: dict[tuple, list[float]] = {}
    cpus: dict[tuple, list[float]] = {}

    def measure(name: str, engine: str, workers: int, cluster, address: str | None, env: dict | None) -> None:
        key = (name, engine, workers)
        out = data / "out" / f"{name}-{engine}-{workers}"
        shutil.rmtree(out, ignore_errors=True)
        engine_args = ["--workers", str(workers)] if engine == "local" else [] if engine == "ray" else ["--cluster", address]
        argv, outputs, units[name] = command(name, paths, out, engine_args)
        if engine == "ray":
            argv = [PY, __file__, "--ray-driver", address, name, *argv[1:]]
        busy.setdefault(key, []).append(wait_for_quiet(args.quiet_below, args.wait))
        loads.setdefault(key, []).append(os.getloadavg()[0])
        if args.bytecode_cache:  # as an installation that keeps compiled modules runs (see --bytecode-cache)
            env = {k: v for k, v in (env or os.environ).items() if k != "PYTHONDONTWRITEBYTECODE"}
            env["PYTHONPYCACHEPREFIX"] = str(data / "pycache")
        wall, client_cpu, unit_cpu, inline = run(argv, env)
        times.setdefault(key, []).append(wall)
        estimates.setdefault(key, []).append(idle_estimate(client_cpu, unit_cpu, workers, inline))
        cpus.setdefault(key, []).append(sum(unit_cpu) + (0 if inline else client_cpu))
        reference.setdefault(name, digest(outputs))
        same[key] = same.get(key, True) and digest(outputs) == reference[name]
        starts[key] = cluster.started if cluster is not None else 0.0
        print(f"{name:15s} {engine:9s} {workers:2d} workers: {wall:6.1f} s (CPU {cpus[key][-1]:.1f} s, idle estimate "
              f"{estimates[key][-1]:.1f} s); before it: load average {loads[key][-1]:.2f}, other work busy {busy[key][-1]:.2f} cores", flush=True)

    for repeat in range(args.repeat):  # interleaved: a busy spell of the machine spreads over all figures
        order = counts if repeat % 2 == 0 else counts[::-1]  # 1, 2 then 2, 1: a drift of the load cancels in the best of two
        for engine in args.engines:
            if engine == "local":  # nothing to start: each command's worker counts back to back
                for name in args.commands:
                    for workers in order:
                        measure(name, engine, workers, None, None, None)
                continue
            for workers in order:  # a cluster per worker count, started before the timing
                cluster, address, env = start_engine(engine, workers)
                try:
                    for name in args.commands:
                        measure(name, engine, workers, cluster, address, env)
                finally:
                    cluster.close()
    rows = []
    for (name, engine, workers), runs in times.items():
        best = min(runs)
        # against one local process, else (local not run) against one worker of the same engine
        reference = (name, "local", 1) if (name, "local", 1) in times else (name, engine, 1)
        base = min(times[reference]) if reference in times else float("nan")
        key = (name, engine, workers)
        estimate = min(estimates[key])
        base_estimate = min(estimates[reference]) if reference in estimates else float("nan")
        rows.append((name, engine, workers, best, 60 * units[name] / best, base / best, same[key], starts[key],
                     f"{min(loads[key]):.1f}-{max(loads[key]):.1f} / {min(busy[key]):.2f}-{max(busy[key]):.2f}", min(cpus[key]), estimate,
                     base_estimate / estimate))
    rows.sort(key=lambda r: (args.commands.index(r[0]), args.engines.index(r[1]), r[2]))
    print(f"\nthe fastest of {args.repeat} run(s) each; units: sequences (evaluate: predictions)")
    print("| command | engine | workers | wall s | units/min | speed-up vs 1 local (else 1 of the engine) | outputs | cluster start, s | before the runs: load "
          "average / other work's busy cores | CPU s | idle estimate s | estimated speed-up |")
    print("|---|---|---|---|---|---|---|---|---|---|---|---|")
    for name, engine, workers, seconds, rate, speedup, identical, started, load, cpu, estimate, estimated in rows:
        print(f"| {name} | {engine} | {workers} | {seconds:.1f} | {rate:.1f} | {speedup:.2f}x | {'identical' if identical else 'DIFFER'} | "
              f"{started:.1f} | {load} | {cpu:.1f} | {estimate:.1f} | {estimated:.2f}x |")
    for name in args.commands:
        two = [r for r in rows if r[0] == name and r[1] == "local" and r[2] == 2]
        if two:
            print(f"goal {name}: {two[0][5]:.2f}x measured, {two[0][11]:.2f}x estimated for an idle machine, with 2 local workers against 1 "
                  f"(goal >= {GOAL}x): {'met' if two[0][5] >= GOAL else 'MISSED'} as measured")
    print(f"load after {os.getloadavg()[0]:.2f}")


if __name__ == "__main__":
    if len(sys.argv) > 1 and sys.argv[1] == "--ray-driver":
        ray_driver()
    else:
        main()
