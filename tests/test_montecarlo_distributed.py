"""Monte Carlo across processes (jax.distributed, CPU collectives over gloo): two local processes
give the same samples and outcomes as one process, sample by sample."""

import socket
import subprocess
import sys
import textwrap

import numpy as np

import jaxland as jl

SPEC = dict(dispersion={"sink_speed_mps": jl.Distribution("truncnormal", 2.0, 0.3, 1.0, 3.0),
                        "mass_scale": jl.Distribution("normal", 1.0, 0.03)},
            fixed={"drop_height_m": 0.0}, n=10, seed=3, t_end=0.2)
CHUNK = 3  # 4 chunks: process 0 runs chunks 0 and 2, process 1 chunks 1 and 3 (the last short)


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def test_two_processes_give_the_one_process_samples_and_outcomes(tmp_path):
    port = _free_port()
    code = textwrap.dedent(f"""
        import sys, numpy as np, jaxland as jl
        rank = int(sys.argv[1])
        jl.init_distributed("127.0.0.1:{port}", 2, rank)
        spec = jl.MonteCarloSpec(
            dispersion={{"sink_speed_mps": jl.Distribution("truncnormal", 2.0, 0.3, 1.0, 3.0),
                         "mass_scale": jl.Distribution("normal", 1.0, 0.03)}},
            fixed={{"drop_height_m": 0.0}}, n=10, seed=3, t_end=0.2)
        r = jl.run_montecarlo(spec, chunk={CHUNK}, progress=False)
        assert r.summary["processes"] == 2
        np.savez(f"{tmp_path}/rank{{rank}}.npz", failure=r.failure,
                 **{{"in_" + k: v for k, v in r.inputs.items()}}, **r.outputs)
    """)
    procs = [subprocess.Popen([sys.executable, "-c", code, str(rank)], stdout=subprocess.PIPE,
                              stderr=subprocess.PIPE, text=True) for rank in (0, 1)]
    outs = [p.communicate(timeout=300) for p in procs]
    for p, (_, err) in zip(procs, outs):
        assert p.returncode == 0, err[-2000:]
    one = jl.run_montecarlo(jl.MonteCarloSpec(**SPEC), chunk=CHUNK, progress=False)
    expected = dict(failure=one.failure, **{"in_" + k: v for k, v in one.inputs.items()},
                    **one.outputs)
    for rank in (0, 1):  # every process holds every sample after the gather
        got = np.load(tmp_path / f"rank{rank}.npz")
        assert set(got.files) == set(expected)
        for k, v in expected.items():
            np.testing.assert_array_equal(got[k], v, err_msg=f"rank {rank}: {k}")
