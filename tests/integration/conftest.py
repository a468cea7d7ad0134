"""The one-node Slurm cluster the integration tests run on."""

import pytest


def _free_port() -> int:
    import socket

    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return sock.getsockname()[1]


@pytest.fixture(scope="session")
def slurm_cluster(tmp_path_factory):
    """A one-node Slurm cluster of this machine (munged, slurmctld, slurmd; `make setup`
    installs them). Yields the environment that points Slurm's commands at it.

    No slurmdbd (it needs a MySQL/MariaDB server): accounting storage is off, and ``sacct
    --completion`` reads the job completion log (jobcomp/filetxt) instead."""
    import os
    import shutil
    import socket
    import subprocess
    import time

    missing = [
        p for p in ("munge", "munged", "slurmctld", "slurmd", "sbatch", "squeue", "scontrol") if shutil.which(p) is None
    ]
    if missing:
        pytest.fail(f"not installed: {', '.join(missing)} (make setup installs slurm-wlm and munge)")
    if not os.path.exists("/usr/lib/x86_64-linux-gnu/pmix2/lib/libpmix.so") and os.path.isdir(
        "/usr/lib/x86_64-linux-gnu/pmix2"
    ):
        pytest.fail("Slurm's PMIx plugin loads pmix2/lib/libpmix.so, which libpmix-dev installs (make setup)")
    if os.geteuid() != 0:
        pytest.skip("starting slurmd needs root (CI runs as root)")
    root = tmp_path_factory.mktemp("slurm")
    for sub in ("state", "spool", "log"):
        (root / sub).mkdir()
    host = socket.gethostname()
    conf = root / "slurm.conf"
    conf.write_text(
        "\n".join(
            [
                "ClusterName=pbmdemtest",
                f"SlurmctldHost={host}",
                "AuthType=auth/munge",
                "CredType=cred/munge",
                "ProctrackType=proctrack/linuxproc",
                "TaskPlugin=task/none",
                "ReturnToService=2",
                "SlurmUser=root",
                "SlurmdUser=root",
                "SchedulerType=sched/backfill",
                "SelectType=select/cons_tres",
                "SelectTypeParameters=CR_Core",
                "JobAcctGatherType=jobacct_gather/none",
                "AccountingStorageType=accounting_storage/none",
                "JobCompType=jobcomp/filetxt",
                f"JobCompLoc={root}/log/jobcomp.txt",
                "MpiDefault=none",
                f"SlurmctldPort={_free_port()}",
                f"SlurmdPort={_free_port()}",
                f"SlurmctldPidFile={root}/slurmctld.pid",
                f"SlurmdPidFile={root}/slurmd.pid",
                f"SlurmdSpoolDir={root}/spool",
                f"StateSaveLocation={root}/state",
                f"SlurmctldLogFile={root}/log/slurmctld.log",
                f"SlurmdLogFile={root}/log/slurmd.log",
                f"NodeName={host} CPUs={os.cpu_count()} State=UNKNOWN",
                "PartitionName=test Nodes=ALL Default=YES MaxTime=INFINITE State=UP",
                "",
            ]
        )
    )
    env = {**os.environ, "SLURM_CONF": str(conf)}
    if subprocess.run(["munge", "-n"], capture_output=True).returncode != 0:
        os.makedirs("/run/munge", exist_ok=True)
        shutil.chown("/run/munge", "munge", "munge")
        subprocess.run(["su", "-s", "/bin/sh", "munge", "-c", "munged"], check=True, capture_output=True)
    for daemon in ("slurmctld", "slurmd"):
        subprocess.run([daemon], env=env, check=True, capture_output=True)
    deadline = time.monotonic() + 60
    while time.monotonic() < deadline:
        state = subprocess.run(["sinfo", "-h", "-o", "%t"], env=env, capture_output=True, text=True).stdout.strip()
        if state == "idle":
            break
        time.sleep(0.5)
    else:
        pytest.fail(f"the one-node cluster did not come up (node state {state!r}); logs in {root / 'log'}")
    yield env
    for name in ("slurmd", "slurmctld"):
        pid_file = root / f"{name}.pid"
        if pid_file.is_file():
            subprocess.run(["kill", pid_file.read_text().strip()], capture_output=True)
