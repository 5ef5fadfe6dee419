"""``hybridhdr simulate dataset SPEC.toml --out DIR``: scenes x sensor profiles x seeds in one command.

Spec (TOML)::

    scenes = ["builtin:window_scenery", "builtin:lamp_shade", "my_scene.toml"]
    seeds = [0, 1, 2]
    profiles = ["clean", "noisy", "builtin:davis240c", "ecd_sensor.json"]   # default ["clean"]

    [options]            # any 'hybridhdr simulate' option, named as its flag without the dashes
    width = 173          # (dashes or underscores): --width 173
    height = 130
    duration_s = 0.5
    no_frames = false    # a true boolean is the bare flag

Every recording is one ``hybridhdr simulate`` command (a profile named ideal/clean/noisy is a
``--preset``, any other a ``--sensor`` profile), run in ``DIR`` and recorded in
``DIR/manifest.json`` with its scene, profile, seed, its exact command line, its counts and the
SHA-256 of its file: the same command in ``DIR`` rebuilds it bit for bit (the renderer variant is
in each recording's provenance; pass ``--variant`` in ``[options]`` to fix it). Relative paths in
the spec are relative to the spec's folder.

The commands run as ``--jobs N`` local processes, or as tasks of a Dask cluster
(``--scheduler ADDRESS``, the engine the bench runner uses; its workers must see ``DIR`` at the
same path and have hybridhdr installed). An interrupt (Ctrl-C, SIGTERM) stops the running commands
with SIGTERM, so each keeps its resumable partial (:mod:`hybridhdr.simulate.resume`);
``--resume`` skips the finished recordings (their hashes checked), finishes the partial ones and
runs the rest: the folder ends up identical to an uninterrupted run's.
"""

from __future__ import annotations

import hashlib
import json
import os
import re
import signal
import subprocess
import sys
import threading
from pathlib import Path

__all__ = ["load_spec", "plan_jobs", "run_dataset", "run_job"]

_FORMAT = "hybridhdr simulate dataset 1"
_PRESETS = ("ideal", "clean", "noisy")
#: options the dataset sets itself, per recording
_RESERVED = {"out", "seed", "preset", "sensor", "json", "resume", "overwrite", "preview", "preview_frames", "list",
             "quiet", "no_progress", "debug", "verbose", "jobs", "scheduler"}
#: the running commands of this process (local mode, or a Dask worker's tasks)
_RUNNING: set = set()
_LOCK = threading.Lock()


def load_spec(path) -> dict:
    """The spec as a dict ``{"scenes", "seeds", "profiles", "options"}``, checked (module notes)."""
    try:
        import tomllib
    except ImportError:  # Python 3.10
        import tomli as tomllib
    path = Path(path)
    try:
        with open(path, "rb") as f:
            d = tomllib.load(f)
    except FileNotFoundError:
        raise FileNotFoundError(f"dataset spec {path} not found") from None
    except tomllib.TOMLDecodeError as e:
        raise ValueError(f"dataset spec {path}: not valid TOML ({e})") from None
    extra = set(d) - {"scenes", "seeds", "profiles", "options"}
    if extra:
        raise ValueError(f"dataset spec {path}: unknown keys {sorted(extra)}; expected scenes, seeds, profiles, options")

    def strings(key, default=None):
        v = d.get(key, default)
        if not isinstance(v, list) or not v or not all(isinstance(x, str) and x for x in v):
            raise ValueError(f"dataset spec {path}: {key} must be a non-empty list of strings, found {v!r}")
        if len(set(v)) != len(v):
            raise ValueError(f"dataset spec {path}: {key} has duplicates: {v}")
        return v
    scenes = strings("scenes")
    profiles = strings("profiles", ["clean"])
    seeds = d.get("seeds")
    if (not isinstance(seeds, list) or not seeds or not all(isinstance(s, int) and not isinstance(s, bool)
                                                            and 0 <= s < 2 ** 63 for s in seeds)):
        raise ValueError(f"dataset spec {path}: seeds must be a non-empty list of integers >= 0, found {seeds!r}")
    if len(set(seeds)) != len(seeds):
        raise ValueError(f"dataset spec {path}: seeds has duplicates: {seeds}")
    opts = d.get("options", {})
    if not isinstance(opts, dict):
        raise ValueError(f"dataset spec {path}: [options] must be a table, found {opts!r}")
    if len(scenes) * len(seeds) * len(profiles) > 100_000:
        raise ValueError(f"dataset spec {path}: {len(scenes) * len(seeds) * len(profiles)} recordings; at most 100000")
    return {"scenes": scenes, "seeds": seeds, "profiles": profiles, "options": opts}


def _slug(s: str) -> str:
    s = s.removeprefix("builtin:")
    s = Path(s).stem if s.endswith((".toml", ".json")) else s
    return re.sub(r"[^A-Za-z0-9_.-]+", "_", s).strip("._") or "x"


def _option_argv(opts: dict) -> list[str]:
    argv = []
    for k, v in opts.items():
        name = k.replace("-", "_")
        if name in _RESERVED:
            raise ValueError(f"dataset spec [options]: {k} is set by the dataset itself (per recording)")
        flag = "--" + name.replace("_", "-")
        if isinstance(v, bool):
            if v:
                argv.append(flag)
        elif isinstance(v, (int, float, str)):
            argv += [flag, str(v)]
        else:
            raise ValueError(f"dataset spec [options]: {k} must be a number, string or boolean, found {v!r}")
    return argv


def plan_jobs(spec: dict, spec_dir: Path) -> list[dict]:
    """One entry per recording: file (relative to the output folder), scene, profile, seed, argv."""
    def resolve(s):
        if s.startswith("builtin:") or s in _PRESETS:
            return s
        p = Path(s)
        return str(p if p.is_absolute() else (spec_dir / p).resolve())
    base = _option_argv(spec["options"])
    jobs, names = [], set()
    for scene in spec["scenes"]:
        for profile in spec["profiles"]:
            for seed in spec["seeds"]:
                name = f"{_slug(scene)}__{_slug(profile)}__seed{seed}.h5"
                if name in names:
                    raise ValueError(f"dataset spec: two recordings would be named {name}; give the scenes or "
                                     f"profiles distinct file names")
                names.add(name)
                prof = ["--preset", profile] if profile in _PRESETS else ["--sensor", resolve(profile)]
                argv = ["simulate", resolve(scene), "--out", f"recordings/{name}", "--seed", str(seed), *prof, *base]
                jobs.append({"file": f"recordings/{name}", "scene": scene, "profile": profile, "seed": seed,
                             "argv": argv})
    return jobs


def _sha256(path: Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def run_job(argv: list[str], cwd: str, resume: bool) -> dict:
    """Run one recording's command in ``cwd`` (in a child process, so that a SIGTERM from an
    interrupt leaves its partial); returns its JSON summary plus the file's SHA-256. Runs on Dask
    workers too (module-level, importable)."""
    cmd = [sys.executable, "-m", "hybridhdr", *argv, "--json", "--no-progress"] + (["--resume"] if resume else [])
    env = dict(os.environ)
    root = str(Path(__file__).resolve().parents[2])  # this hybridhdr, also in the child
    env["PYTHONPATH"] = root + (os.pathsep + env["PYTHONPATH"] if env.get("PYTHONPATH") else "")
    p = subprocess.Popen(cmd, cwd=cwd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env)
    with _LOCK:
        _RUNNING.add(p)
    try:
        out, err = p.communicate()
    finally:
        with _LOCK:
            _RUNNING.discard(p)
    if p.returncode != 0:
        lines = [ln for ln in err.splitlines() if ln.strip()]
        raise RuntimeError(f"'hybridhdr {' '.join(argv)}' failed (exit {p.returncode}): "
                           f"{lines[-1] if lines else 'no message'}")
    summary = json.loads(out.strip().splitlines()[-1])
    out_path = Path(cwd) / argv[argv.index("--out") + 1]
    return {"events": summary["events"], "frames": summary["frames"], "hdr_references": summary["hdr_references"],
            "renders": summary["renders"], "variant": summary["variant"], "sha256": _sha256(out_path),
            "wall_s": summary["wall_s"], "renders_reused": summary["renders_reused"]}


def terminate_running() -> int:
    """SIGTERM every command this process runs (they keep their partials); returns how many."""
    with _LOCK:
        procs = list(_RUNNING)
    for p in procs:
        try:
            p.send_signal(signal.SIGTERM)
        except OSError:
            pass
    return len(procs)


def _write_manifest(path: Path, manifest: dict) -> None:
    from .._util.atomic import atomic_path
    with atomic_path(path) as tmp, open(tmp, "w", encoding="utf-8") as f:
        json.dump(manifest, f, indent=1)
        f.write("\n")


def run_dataset(args, say, check_argv=None) -> dict:
    """The command (module notes); returns the summary. ``check_argv(argv)`` checks a recording's
    command line before any work (raises SystemExit on a bad one: the command's parser)."""
    from .._util.atomic import refuse_existing_output
    from .._version import __version__
    if not args.spec:
        raise ValueError("simulate dataset: give the spec, 'hybridhdr simulate dataset SPEC.toml --out DIR'")
    if args.out is None:
        raise ValueError("simulate dataset: --out DIR is required")
    spec_path = Path(args.spec)
    spec = load_spec(spec_path)
    jobs = plan_jobs(spec, spec_path.resolve().parent)
    for j in jobs[:: max(1, len(jobs) // 8)] + jobs[-1:] if check_argv else []:  # checked before any work
        try:
            check_argv(j["argv"])
        except SystemExit:
            raise ValueError(f"dataset spec {spec_path}: [options] give an invalid command: "
                             f"'hybridhdr {' '.join(j['argv'])}' (see the message above)") from None
    out = Path(args.out)
    mpath = out / "manifest.json"
    old = {}
    if args.resume:
        if not mpath.exists():
            raise ValueError(f"--resume: {mpath} not found (a 'simulate dataset' run writes it first)")
        m = json.loads(mpath.read_text(encoding="utf-8"))
        if m.get("spec") != spec:
            raise ValueError(f"--resume: {mpath} was made from another spec; use the same SPEC.toml, or --overwrite")
        old = {r["file"]: r for r in m.get("recordings", []) if r.get("done")}
    else:
        refuse_existing_output(out, overwrite=args.overwrite, flag="--out", command="simulate dataset")
    (out / "recordings").mkdir(parents=True, exist_ok=True)
    from .resume import partial_path
    records, todo = [], []
    for j in jobs:
        r = {k: j[k] for k in ("file", "scene", "profile", "seed", "argv")}
        r["done"] = False
        f = out / j["file"]
        if j["file"] in old and f.exists() and _sha256(f) == old[j["file"]].get("sha256"):
            r.update({k: old[j["file"]][k] for k in ("done", "events", "frames", "hdr_references", "renders",
                                                       "variant", "sha256")})
        else:
            if not args.resume:
                f.unlink(missing_ok=True)
                partial_path(f).unlink(missing_ok=True)
            elif f.exists():  # finished but not recorded (interrupted in between): made again
                f.unlink()
            todo.append(len(records))
        records.append(r)
    manifest = {"format": _FORMAT, "hybridhdr_version": __version__, "spec": spec,
                "rebuild": "each recording: 'hybridhdr ARGV' run in this folder (argv below)",
                "recordings": records}
    _write_manifest(mpath, manifest)
    say(f"simulate dataset: {len(jobs)} recordings ({len(spec['scenes'])} scenes x {len(spec['profiles'])} profiles x "
        f"{len(spec['seeds'])} seeds), {len(jobs) - len(todo)} already done, "
        + (f"on the Dask scheduler {args.scheduler}" if args.scheduler else f"{args.jobs} local processes"))
    cwd = str(out.resolve())
    failures = []
    wall = {}

    def finished(i, res):
        r = records[i]
        wall[r["file"]] = res.pop("wall_s")
        res.pop("renders_reused")
        r.update(res, done=True)
        _write_manifest(mpath, manifest)

    pbar = None
    if not args.no_progress:
        from tqdm.auto import tqdm
        pbar = tqdm(total=len(todo), unit="rec", desc="simulate dataset", leave=False)
    try:
        if args.scheduler:
            _run_dask(args.scheduler, records, todo, cwd, out, finished, failures, pbar)
        else:
            _run_local(args.jobs, records, todo, cwd, out, finished, failures, pbar)
    except BaseException as e:
        n = terminate_running()
        _write_manifest(mpath, manifest)
        done = sum(r["done"] for r in records)
        if isinstance(e, (KeyboardInterrupt, SystemExit)):
            say(f"interrupted: {done} of {len(records)} recordings done, {n} stopped with their partials kept; "
                f"run the same command with --resume to finish")
        raise
    finally:
        if pbar is not None:
            pbar.close()
    if failures:
        raise RuntimeError(f"{len(failures)} of {len(todo)} recordings failed (the others are done; --resume retries "
                           f"them): {failures[0]}")
    return {"out": str(out), "manifest": str(mpath), "recordings": len(records), "ran": len(todo),
            "events": sum(r["events"] for r in records), "wall_s": wall}


def _run_local(n_jobs, records, todo, cwd, out, finished, failures, pbar):
    from concurrent.futures import ThreadPoolExecutor, as_completed

    from .resume import partial_path
    # threads only wait on the child processes (the work is in the children)
    with ThreadPoolExecutor(max_workers=max(1, int(n_jobs))) as ex:
        futs = {ex.submit(run_job, records[i]["argv"], cwd, partial_path(out / records[i]["file"]).exists()): i
                for i in todo}
        try:
            for fu in as_completed(futs):
                try:
                    finished(futs[fu], fu.result())
                except RuntimeError as e:
                    failures.append(str(e))
                if pbar is not None:
                    pbar.update(1)
        except BaseException:
            for fu in futs:
                fu.cancel()
            terminate_running()
            raise


def _run_dask(address, records, todo, cwd, out, finished, failures, pbar):
    try:
        from distributed import Client, as_completed
    except ImportError as e:
        raise ImportError("--scheduler needs Dask: pip install 'dask[distributed]' (the [evaluate] extra)") from e
    from .resume import partial_path
    with Client(address) as client:
        futs = {client.submit(run_job, records[i]["argv"], cwd, partial_path(out / records[i]["file"]).exists(),
                              pure=False, key=f"simulate-{Path(records[i]['file']).stem}-{os.getpid()}"): i
                for i in todo}
        try:
            for fu in as_completed(list(futs)):
                try:
                    finished(futs[fu], fu.result())
                except RuntimeError as e:
                    failures.append(str(e))
                if pbar is not None:
                    pbar.update(1)
        except BaseException:
            client.cancel(list(futs))
            try:  # the workers' running commands keep their partials
                client.run(terminate_running)
            except Exception:  # noqa: BLE001 - the cluster may be gone
                pass
            raise
