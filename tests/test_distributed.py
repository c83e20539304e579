"""Several processes: a study across two local processes (``jax.distributed`` on CPU, gloo collectives)
gives the same table as one process. The cluster recipe of docs/sweeps.md runs the same code under SLURM."""

from __future__ import annotations

import os
import socket
import subprocess
import sys

import pytest

SCRIPT = """
import sys
import jax
pid, n, port, folder = int(sys.argv[1]), int(sys.argv[2]), sys.argv[3], sys.argv[4]
if n > 1:
    jax.config.update("jax_cpu_collectives_implementation", "gloo")
    jax.distributed.initialize(coordinator_address=f"localhost:{port}", num_processes=n, process_id=pid)
import hybridslam as hs
from hybridslam.studies import study
spec = study.AlphaStudy(alphas=(0.1, 0.4), models=("mirror",), tracks=4, steps=3,
                        estimator=hs.Hybrid(weights=hs.Linearized(), capacity=4, smoother=hs.estimators.smoothing.Filter()))
rows = study.run_alpha_study(spec, folder)
print("process", jax.process_index(), "of", jax.process_count(), "devices", len(jax.devices()), "rows", len(rows))
"""


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("localhost", 0))
        return s.getsockname()[1]


@pytest.mark.slow  # two processes compiling the sweep, a minute: the extended suite, CI
def test_two_processes_give_the_single_process_table(tmp_path, shared_compilation_cache):
    env = {k: v for k, v in os.environ.items() if k != "XLA_FLAGS"}  # one CPU device per process
    one, two = tmp_path / "one", tmp_path / "two"
    # The single-process reference runs here (one process fewer to start and compile); tables do not
    # depend on the number of devices (test_sweep.py), so this process's device count does not matter.
    import hybridslam as hs
    from hybridslam.studies import study

    namespace = {"hs": hs}
    exec(SCRIPT.split("import hybridslam as hs", 1)[1].split("rows = ")[0], namespace)  # noqa: S102 (the same spec)
    study.run_alpha_study(namespace["spec"], str(one))
    port = str(_free_port())
    procs = [subprocess.Popen([sys.executable, "-c", SCRIPT, str(i), "2", port, str(two)], env=env,
                              stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True) for i in range(2)]
    outs = [p.communicate(timeout=600) for p in procs]
    for p, (out, err) in zip(procs, outs):
        assert p.returncode == 0, err
        assert "of 2 devices 2 rows 24" in out, out
    assert (two / "table.csv").read_text() == (one / "table.csv").read_text()
    records = (two / "cells.jsonl").read_text().splitlines()
    assert len(records) == 1 + 2 and all('"devices": 2' in line for line in records[1:])


if __name__ == "__main__":  # pragma: no cover
    sys.exit(pytest.main([__file__]))
