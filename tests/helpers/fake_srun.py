"""Stands in for ``srun`` where tests have no SLURM: ``python tests/helpers/fake_srun.py <tasks> <command>``
starts ``<tasks>`` copies of the command on this machine with the variables SLURM gives the
tasks of a job step on as many nodes, one task each (``SLURM_PROCID``, ``SLURM_NODEID``,
``SLURM_NTASKS``...), and ends the step as ``srun --kill-on-bad-exit`` does: the first task that
fails kills the others and its code is the step's."""

import os
import subprocess
import sys
import time


def main() -> int:
    tasks, command = int(sys.argv[1]), sys.argv[2:]
    procs = []
    for task in range(tasks):
        env = {**os.environ, "SLURM_NTASKS": str(tasks), "SLURM_PROCID": str(task),
               "SLURM_LOCALID": "0", "SLURM_NODEID": str(task), "SLURM_NNODES": str(tasks),
               "SLURM_NTASKS_PER_NODE": "1", "SLURM_JOB_NAME": "trial", "SLURM_JOB_ID": "4242",
               "SLURM_NODELIST": "127.0.0.1", "MASTER_ADDR": "127.0.0.1"}  # fmt: skip
        procs.append(subprocess.Popen(command, env=env))
    while True:
        codes = [p.poll() for p in procs]
        for task, code in enumerate(codes):
            if code not in (None, 0):
                for proc in procs:
                    if proc.poll() is None:
                        proc.kill()
                sys.stderr.write(f"srun: error: task {task}: Exited with exit code {code}\n")
                return code if code > 0 else 1
        if all(code == 0 for code in codes):
            return 0
        time.sleep(0.1)


if __name__ == "__main__":
    sys.exit(main())
