"""DEM runs as one Slurm job array, followed through ``sacct``.

* :func:`submit_array` -- the runs of a set of configurations that are neither cached nor
  shipped, as one ``sbatch --array`` whose task *i* is the ordinary ``pbmdem dem run`` of
  configuration *i* (LIGGGHTS started by ``srun``, :func:`dem.cluster.under_srun`; the
  results in the cache a local run uses), with a manifest (``manifest.json``: array job id,
  task index -> configuration and results key) in a folder of its own. It returns at once.
* :func:`array_status` -- every task's state from ``sacct`` (pending, running, completed,
  failed) and, once completed, its results file.
* :func:`resubmit` -- failed tasks as a new array; a task whose run left restart files
  resumes from them (``--resume``).
* :func:`run_campaign_on_slurm` -- the validation campaign through the same three, followed
  until every run has ended (``pbmdem validate --scheduler slurm``).

Why plain ``sbatch`` arrays and not submitit (installable: ``pip download submitit``
works): submitit pickles a Python function and starts it with ``srun`` on every task of
the job, so LIGGGHTS' MPI ranks would have to be started again from inside Python; here
``srun`` starts LIGGGHTS itself, the job is a shell script anyone can read and resubmit,
and its state comes from ``sacct`` even without submitit's pickles on disk.

``sacct`` without slurmdbd. Slurm 22.05 has no accounting storage but slurmdbd (whose only
back end is MySQL/MariaDB); without it ``sacct`` answers "Slurm accounting storage is
disabled". ``sacct --completion`` then reads the job completion log
(``JobCompType=jobcomp/filetxt``), which lists ended jobs by their own job id only, not as
``<array id>_<index>``: each task writes its id to ``<array id>_<index>.jobid`` when it
starts (:func:`dem.cluster.array_script`), and pending or running tasks, which that log
does not hold, are read from ``squeue``.
"""

from __future__ import annotations

import json
import os
import re
import shlex
import shutil
import subprocess
import sys
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass, replace
from pathlib import Path

from coupling.cache import cache_path
from coupling.errors import ConfigError, SolverRunError
from coupling.files import locked, replace_file, writable_directory
from dem.cluster import array_script, check_tasks, under_srun
from dem.run import can_resume, prepare_run
from workflows.config import Config, dump_toml, load_config
from workflows.pipeline.cluster import cost_estimate
from workflows.pipeline.log import Log, quiet
from workflows.pipeline.stages import dem_stage, post_hash, results_available, results_key
from workflows.shipped import SHIPPED_RESULTS_DIRS

MANIFEST = "manifest.json"
#: the folder of the scripts, the tasks' output and job-id records, inside the manifest's
JOBS_DIR = "slurm"
CONFIGS_DIR = "configs"

#: Slurm's job states by what they mean for a task (anything else: failed)
PENDING_STATES = frozenset({"PENDING", "REQUEUED", "REQUEUE_FED", "REQUEUE_HOLD", "RESIZING", "SUSPENDED"})
RUNNING_STATES = frozenset({"RUNNING", "COMPLETING", "CONFIGURING", "STAGE_OUT", "SIGNALING"})
COMPLETED_STATES = frozenset({"COMPLETED"})

TASK_STATES = ("pending", "running", "completed", "failed")
#: where the jobs start: the folder this package is imported from, so that ``python -m
#: workflows.cli`` in a job runs this code wherever the build was started
CODE_ROOT = Path(__file__).resolve().parents[2]


# ----------------------------------------------------------------------------- sacct's text
@dataclass(frozen=True)
class JobRecord:
    """One job (an array task: ``<array id>_<index>``) as ``sacct`` or ``squeue`` lists it:
    Slurm's state word (``CANCELLED by 0`` -> ``CANCELLED``), exit code and elapsed time."""

    job: str
    state: str
    exit_code: str = ""
    elapsed: str = ""

    @property
    def task_state(self) -> str:
        return task_state(self.state)


def task_state(slurm_state: str) -> str:
    """pending, running, completed or failed for one of Slurm's job states."""
    word = slurm_state.split()[0].rstrip("+") if slurm_state.split() else ""
    if word in PENDING_STATES:
        return "pending"
    if word in RUNNING_STATES:
        return "running"
    return "completed" if word in COMPLETED_STATES else "failed"


_ARRAY_RANGE = re.compile(r"^(\d+)_\[([^\]]*)\]$")


def parse_sacct(text: str) -> dict[str, JobRecord]:
    """The jobs of ``sacct -P -n --format=JobID,State,ExitCode,Elapsed`` (or ``squeue -h -o
    '%i|%T|...'``) output, by job id. A job step (``123_4.batch``, ``123.0``) is left out:
    its job's own line says how the job ended. A line of pending tasks listed together
    (``123_[5-7,9%2]``) gives one record per task."""
    jobs: dict[str, JobRecord] = {}
    for line in text.splitlines():
        fields = [f.strip() for f in line.split("|")]
        if len(fields) < 2 or not fields[0] or "." in fields[0]:
            continue
        job, state = fields[0], fields[1]
        exit_code, elapsed = (fields[2:4] + ["", ""])[:2]
        grouped = _ARRAY_RANGE.match(job)
        ids = [f"{grouped.group(1)}_{i}" for i in _indices(grouped.group(2))] if grouped else [job]
        for job_id in ids:
            jobs[job_id] = JobRecord(job_id, state.split()[0] if state.split() else "", exit_code, elapsed)
    return jobs


def _indices(spec: str) -> list[int]:
    """The task indices of an ``--array`` value (``0-3,7,9-13:2%4``: a step after ``:``, a
    limit of running tasks after ``%``)."""
    out: list[int] = []
    for part in spec.split("%")[0].split(","):
        if not part:
            continue
        span, _, step = part.partition(":")
        first, _, last = span.partition("-")
        out += range(int(first), int(last or first) + 1, int(step or 1))
    return out


def _slurm(args: list[str], env: dict[str, str] | None, check: bool = True) -> subprocess.CompletedProcess:
    try:
        done = subprocess.run(args, env=env, capture_output=True, text=True, timeout=120)
    except (OSError, subprocess.TimeoutExpired) as exc:
        raise SolverRunError(f"{args[0]} could not run: {exc}") from None
    if check and done.returncode != 0:
        raise SolverRunError(f"{shlex.join(args)} failed: {said(done)}")
    return done


def said(done: subprocess.CompletedProcess) -> str:
    """What a Slurm command printed (its stderr, else its stdout) on one line, the last
    500 characters: the error is printed as one line."""
    return "; ".join(line.strip() for line in (done.stderr or done.stdout).splitlines() if line.strip())[-500:]


SACCT_FORMAT = "--format=JobID,State,ExitCode,Elapsed"


def job_records(array_ids: list[str], jobs_dir: Path, env: dict[str, str] | None = None) -> dict[str, JobRecord]:
    """The tasks of the arrays ``array_ids``, by ``<array id>_<index>``: ``sacct`` (the
    accounting database, else the job completion log, see the module's notes) for every
    task it knows, ``squeue`` for the ones still queued or running, an ended state from
    ``sacct`` taking precedence over ``squeue``'s. A task neither lists is absent."""
    if not array_ids:
        return {}
    # first the queue, then the accounting: a task that ends in between is then still found
    queue = _slurm(["squeue", "-h", "-r", "--me", "-o", "%i|%T|0:0|%M"], env).stdout
    live = {job: rec for job, rec in parse_sacct(queue).items() if job.split("_")[0] in array_ids}
    accounted = _slurm(["sacct", "-j", ",".join(array_ids), SACCT_FORMAT, "-P", "-n"], env, check=False)
    if accounted.returncode == 0:
        ended = parse_sacct(accounted.stdout)
    elif "accounting storage is disabled" in (accounted.stderr + accounted.stdout).lower():
        ended = _completion_records(array_ids, jobs_dir, env)
    else:
        raise SolverRunError(f"sacct failed: {said(accounted)}")
    records = dict(live)
    for job, rec in ended.items():
        if job not in records or rec.task_state in ("completed", "failed"):
            records[job] = rec
    return records


def _completion_records(array_ids: list[str], jobs_dir: Path, env: dict[str, str] | None) -> dict[str, JobRecord]:
    """Ended tasks from ``sacct --completion``, renamed from their own job ids to
    ``<array id>_<index>`` by the records the tasks wrote; none when the cluster keeps no
    completion log either (then the cache alone says how a task ended)."""
    own = {}
    for path in jobs_dir.glob("*.jobid"):
        if path.stem.split("_")[0] in array_ids:
            text = path.read_text().strip()
            if text:
                own[text] = path.stem
    if not own:
        return {}
    done = _slurm(["sacct", "--completion", "-j", ",".join(sorted(own)), SACCT_FORMAT, "-P", "-n"], env, check=False)
    if done.returncode != 0:
        return {}
    return {own[job]: replace(rec, job=own[job]) for job, rec in parse_sacct(done.stdout).items() if job in own}


# ----------------------------------------------------------------------------- the manifest
@dataclass(frozen=True)
class ArrayTask:
    """One configuration of a build: its array ``index`` and ``name``, its resolved
    ``config_file`` (relative to the manifest's folder), the ``key`` of its results file
    (``dem-<key>.h5``; None when no solver was found to key it at submission), the array
    ``job`` of its latest submission (None: its results were there, no job) and the
    ``attempts`` submitted."""

    index: int
    name: str
    config_file: str
    key: str | None
    job: str | None
    attempts: int

    @property
    def job_id(self) -> str | None:
        """The task's Slurm id, ``<array id>_<index>``."""
        return None if self.job is None else f"{self.job}_{self.index}"


@dataclass(frozen=True)
class Manifest:
    """A build: the runs directory its tasks run in (whose ``cache/`` takes their results),
    the MPI ranks of each (None: each configuration's), the partition, the folders of
    shipped results that serve without a run, and its tasks."""

    runs_dir: str
    np: int | None
    partition: str | None
    reference_dirs: tuple[str, ...]
    tasks: tuple[ArrayTask, ...]

    def record(self) -> dict:
        return asdict(self)

    @classmethod
    def from_record(cls, data: dict) -> Manifest:
        tasks = tuple(ArrayTask(**t) for t in data["tasks"])
        return cls(data["runs_dir"], data["np"], data["partition"], tuple(data["reference_dirs"]), tasks)


def read_manifest(folder: str | Path) -> Manifest:
    path = Path(folder) / MANIFEST
    try:
        return Manifest.from_record(json.loads(path.read_text()))
    except FileNotFoundError:
        raise ConfigError(
            f"{folder} holds no build ({MANIFEST} not found); start one with `pbmdem library build`"
        ) from None
    except (OSError, ValueError, KeyError, TypeError) as exc:
        raise ConfigError(f"{path} is not a build manifest: {exc}") from None


def write_manifest(folder: str | Path, manifest: Manifest) -> Path:
    return replace_file(Path(folder) / MANIFEST, json.dumps(manifest.record(), indent=2) + "\n", "build manifest")


def task_config(folder: str | Path, task: ArrayTask) -> Config:
    return load_config(Path(folder) / task.config_file)


def prepare_tasks(
    configs: dict[str, Config], folder: str | Path, srun: bool = True
) -> tuple[Path, tuple[ArrayTask, ...]]:
    """The build's folder made and each configuration written into ``configs/<name>.toml``,
    with ``srun``, LIGGGHTS started by ``srun`` for a job (the launcher is not part of the
    run's key: a local request finds the run). Refused before anything is written: a name
    that is not a file name, two configurations that make the same DEM run (their tasks
    would claim one run directory)."""
    seen: dict[tuple[str, str], str] = {}
    keyed = []
    for name, config in configs.items():
        if not re.fullmatch(r"[\w.+-]+", name) or name.startswith("."):
            raise ConfigError(f"run name {name!r} cannot name a file; use letters, digits and . _ + -")
        inputs = prepare_run(config.dem)
        post = post_hash(config)
        same = seen.setdefault((inputs.deck_hash, post), name)
        if same != name:
            raise ConfigError(f"{same} and {name} make the same DEM run (deck {inputs.deck_hash}); keep one of them")
        keyed.append((name, config, None if inputs.key is None else results_key(inputs.key, post)))
    folder = writable_directory(folder, "library folder").resolve()
    writable_directory(folder / CONFIGS_DIR, "configurations folder")
    writable_directory(folder / JOBS_DIR, "Slurm jobs folder")
    tasks = []
    for index, (name, config, key) in enumerate(keyed):
        relative = f"{CONFIGS_DIR}/{name}.toml"
        written = config.model_copy(update={"dem": under_srun(config.dem)}) if srun else config
        replace_file(folder / relative, dump_toml(written), "configuration")
        tasks.append(ArrayTask(index, name, relative, key, None, 0))
    return folder, tuple(tasks)


# ----------------------------------------------------------------------------- submission
def task_command(config_file: Path, runs_root: Path, np: int, resume: bool) -> list[str]:
    """A task's one command: the ordinary ``pbmdem dem run`` (LIGGGHTS, the post-processing,
    the cache), so a run made on Slurm is found like a local one."""
    command = [sys.executable, "-m", "workflows.cli", "dem", "run", "--config", str(config_file)]
    command += ["--runs-dir", str(runs_root), "--np", str(np), "--no-progress"]
    return command + (["--resume"] if resume else [])


def array_ranks(folder: Path, manifest: Manifest) -> int:
    """MPI ranks of every task: the build's, else the largest of its configurations' (one
    array asks for one number of tasks, and srun starts that many)."""
    if manifest.np is not None:
        return manifest.np
    return max(task_config(folder, t).dem.run.np for t in manifest.tasks)


def _wall_hours(configs: list[Config], np: int, log: Log) -> float | None:
    try:
        return max(cost_estimate(config, np)[0].wall_hours for config in configs)
    except ConfigError as exc:
        log(f"slurm: no wall-time estimate ({exc}); the partition's default time limit applies")
        return None


def _submit(folder: Path, manifest: Manifest, indices: list[int], env, log: Log) -> Manifest:
    """Tasks ``indices`` of ``manifest`` as one new array (resuming those with restart files);
    the manifest with their job and attempts, written."""
    runs_root = Path(manifest.runs_dir)
    np = array_ranks(folder, manifest)
    jobs_dir = folder / JOBS_DIR
    commands, configs, resumed = {}, [], []
    for i in indices:
        task = manifest.tasks[i]
        config = task_config(folder, task)
        resume = can_resume(prepare_run(config.dem), runs_root)
        commands[i] = task_command(folder / task.config_file, runs_root, np, resume)
        configs.append(config)
        if resume:
            resumed.append(task.name)
    script = jobs_dir / f"array-{len(list(jobs_dir.glob('array-*.sh'))) + 1}.sh"
    text = array_script(
        commands,
        str(CODE_ROOT),
        np,
        _wall_hours(configs, np, log),
        str(jobs_dir),
        job_name=f"pbmdem-{folder.name}",
        partition=manifest.partition,
    )
    replace_file(script, text, "job array script")
    job = _slurm(["sbatch", "--parsable", str(script)], env).stdout.strip().split(";")[0]
    if not job.isdigit():
        raise SolverRunError(f"sbatch {script} printed {job!r}, not a job id")
    tasks = list(manifest.tasks)
    for i in indices:
        tasks[i] = replace(tasks[i], job=job, attempts=tasks[i].attempts + 1)
    manifest = replace(manifest, tasks=tuple(tasks))
    write_manifest(folder, manifest)
    names = ", ".join(manifest.tasks[i].name for i in indices)
    log(
        f"slurm: job array {job} ({len(indices)} task(s): {names})"
        + (f"; resuming from restart files: {', '.join(resumed)}" if resumed else "")
    )
    return manifest


def refuse_live_build(folder: str | Path, env: dict[str, str] | None = None) -> None:
    """ConfigError while an earlier build in ``folder`` has tasks queued or running: a new
    manifest would lose their job ids, and their results would not be added."""
    if (Path(folder) / MANIFEST).is_file():
        # Slurm's word alone: a task without a job, or one ended, is not live whatever its files
        tasks = [t for t in read_manifest(folder).tasks if t.job is not None]
        records = job_records(sorted({t.job for t in tasks}), Path(folder) / JOBS_DIR, env)
        live = [
            t.job_id for t in tasks if t.job_id in records and records[t.job_id].task_state in ("pending", "running")
        ]
        if live:
            raise ConfigError(
                f"{folder} has a build with tasks still queued or running ({', '.join(live)}); "
                "wait for them (`pbmdem library status`) or use another folder"
            )


def submit_array(
    configs: dict[str, Config],
    folder: str | Path,
    runs_root: str | Path = "runs",
    np: int | None = None,
    partition: str | None = None,
    env: dict[str, str] | None = None,
    log: Log = quiet,
    reference_dir: Path | tuple[Path, ...] = SHIPPED_RESULTS_DIRS,
) -> Manifest:
    """Every configuration in ``configs`` (name -> configuration) a task of one job array
    run in ``runs_root``, unless its results are cached or in ``reference_dir`` (or its run
    completed there): that one is recorded without a job. Writes the manifest and the
    script into ``folder`` and returns at once. Refused while an earlier build in
    ``folder`` still has tasks queued or running. ``env``: the environment of the Slurm
    commands (e.g. SLURM_CONF)."""
    if not configs:
        raise ConfigError("nothing to build: give at least one configuration")
    if shutil.which("sbatch", path=(env or os.environ).get("PATH")) is None:
        raise ConfigError("sbatch not found on PATH: a Slurm build needs Slurm's commands (or --scheduler local)")
    if np is not None:
        check_tasks(np)
    refuse_live_build(folder, env)
    runs_root = writable_directory(runs_root, "runs directory").resolve()
    refs = (reference_dir,) if isinstance(reference_dir, (str, Path)) else tuple(reference_dir)
    folder, tasks = prepare_tasks(configs, folder)
    manifest = Manifest(str(runs_root), np, partition, tuple(str(Path(d).resolve()) for d in refs), tasks)
    with locked(folder / MANIFEST, "build manifest"):
        write_manifest(folder, manifest)
        missing = [t.index for t, c in zip(tasks, configs.values()) if not results_available(c, runs_root, refs)]
        for t in tasks:
            if t.index not in missing:
                log(f"slurm: {t.name} needs no job (cached, shipped or completed)")
        return _submit(folder, manifest, missing, env, log) if missing else manifest


def resubmit(
    folder: str | Path, tasks: list[ArrayTask], env: dict[str, str] | None = None, log: Log = quiet
) -> Manifest:
    """``tasks`` of the build in ``folder`` (as a status saw them) submitted again as one
    array; a task whose run left restart files resumes from them. A task submitted again
    since it was seen (another ``status --resubmit-failed``) is left alone."""
    folder = Path(folder).resolve()
    with locked(folder / MANIFEST, "build manifest"):
        manifest = read_manifest(folder)
        current = {t.index: t for t in manifest.tasks}
        indices = sorted({t.index for t in tasks if t.index in current and current[t.index].job == t.job})
        return _submit(folder, manifest, indices, env, log) if indices else manifest


# ----------------------------------------------------------------------------- status
@dataclass(frozen=True)
class TaskStatus:
    """A task's ``state`` (pending, running, completed, failed), Slurm's own word for it
    (empty when no job ran), the job's elapsed time, its ``results`` file once completed,
    and, when failed, the ``reason`` (the job's output file)."""

    task: ArrayTask
    state: str
    slurm_state: str = ""
    elapsed: str = ""
    results: Path | None = None
    reason: str = ""


def _results_file(folder: Path, manifest: Manifest, task: ArrayTask) -> Path | None:
    """The task's results file in the cache or a shipped folder, None when there is none.
    A keyed task's cache file is taken as it is (its job wrote it after checking it):
    a status of a large library does not read every results file again."""
    if task.key is not None and cache_path(Path(manifest.runs_dir) / "cache", task.key).is_file():
        return cache_path(Path(manifest.runs_dir) / "cache", task.key)
    config = task_config(folder, task)
    refs = tuple(Path(d) for d in manifest.reference_dirs)
    try:
        return dem_stage(config, manifest.runs_dir, solver=False, reference_dir=refs).cache_file
    except LookupError:
        return None


def array_status(folder: str | Path, env: dict[str, str] | None = None) -> tuple[TaskStatus, ...]:
    """Every task of the build in ``folder``: its state from ``sacct`` / ``squeue``
    (:func:`job_records`), a completed one with its results file. A task whose job ended
    completed but left no results, or whose job neither ``sacct`` nor ``squeue`` knows and
    whose results are missing, is failed."""
    folder = Path(folder).resolve()
    manifest = read_manifest(folder)
    arrays = sorted({t.job for t in manifest.tasks if t.job is not None})
    records = job_records(arrays, folder / JOBS_DIR, env)
    out = []
    for task in manifest.tasks:
        record = records.get(task.job_id) if task.job is not None else None
        state = record.task_state if record is not None else None
        status = TaskStatus(task, state or "failed", *((record.state, record.elapsed) if record else ("", "")))
        if state in ("pending", "running"):
            out.append(status)
            continue
        results = _results_file(folder, manifest, task) if state in (None, "completed") else None
        if results is not None:
            out.append(replace(status, state="completed", results=results))
            continue
        output = folder / JOBS_DIR / f"{task.job_id}.out"
        reason = (
            "no job ran and no results are found"
            if task.job is None
            else f"job {task.job_id} ended {record.state} (exit {record.exit_code}); its output: {output}"
            if record is not None and state == "failed"
            else f"job {task.job_id} ended without results in the cache; its output: {output}"
        )
        out.append(replace(status, state="failed", reason=reason))
    return tuple(out)


#: seconds between looks at the jobs
POLL_S = 30.0
#: submissions of one run before it is given up: the first, then resumes from its restart files
MAX_ATTEMPTS = 3


def run_campaign_on_slurm(
    configs: dict[str, Config],
    runs_root: str | Path,
    np: int | None,
    log: Log,
    partition: str | None = None,
    env: dict[str, str] | None = None,
    poll_s: float = POLL_S,
    max_attempts: int = MAX_ATTEMPTS,
    reference_dir: Path | tuple[Path, ...] | None = None,
    watch: Callable[[tuple[TaskStatus, ...]], None] | None = None,
) -> dict[str, TaskStatus]:
    """Every run of ``configs`` that is neither cached, shipped nor completed under
    ``runs_root``, a task of one Slurm job array of ``np`` ranks each (default: the largest
    ``dem.run.np`` of the configs) -- :func:`submit_array`, as
    ``pbmdem library build`` -- with its manifest in ``<runs_root>/slurm``; followed through
    :func:`array_status` until no task is queued or running, a
    failed task resubmitted (resuming from its restart files) up to ``max_attempts``
    submissions. ``env``: the environment of the Slurm commands (e.g. SLURM_CONF);
    ``watch``: called with the tasks' states after every look. Returns every run's state by
    name; the results are then the cache's, like a local campaign's."""
    runs_root = writable_directory(runs_root, "runs directory").resolve()
    shipped = {} if reference_dir is None else {"reference_dir": reference_dir}
    folder = runs_root / "slurm"
    submit_array(configs, folder, runs_root, np, partition, env, log, **shipped)
    while True:
        states = array_status(folder, env)
        if watch is not None:
            watch(states)
        retry = [s for s in states if s.state == "failed" and s.task.job is not None and s.task.attempts < max_attempts]
        for s in retry:
            log(f"slurm: {s.task.name} failed ({s.reason}); submitting it again")
        if retry:
            resubmit(folder, [s.task for s in retry], env, log)
        elif not any(s.state in ("pending", "running") for s in states):
            return {s.task.name: s for s in states}
        time.sleep(poll_s)
