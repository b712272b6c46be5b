"""The benchmark scripts (benchmarks/): a smoke run, and smoke runs never touch the tracked
results in benchmarks/results/."""

import json
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
BENCH = ROOT / "benchmarks"
sys.path.insert(0, str(BENCH))

import _common  # noqa: E402


def _results_status() -> str:
    """git status of what these scripts write in benchmarks/results (only those paths: other
    people may be editing other results files in a shared working tree meanwhile), plus the
    modification times of the ignored raw dumps."""
    paths = ["benchmarks/results/bench_landing.json", "benchmarks/results/bench_landing.png",
             "benchmarks/results/bench_landing_accelerator*",
             "benchmarks/results/integrators.json", "benchmarks/results/integrators_*.png"]
    status = subprocess.run(["git", "status", "--porcelain", "--", *paths], cwd=ROOT,
                            capture_output=True, text=True, check=True).stdout
    raw = sorted((p.name, p.stat().st_mtime_ns) for p in _common.RAW.glob("*"))
    return f"{status}{raw}"


def test_quick_defaults_outside_the_tracked_results():
    quick = _common.out_dir(None, quick=True)
    assert quick == _common.QUICK_OUT
    assert _common.RESULTS not in quick.parents and quick != _common.RESULTS
    assert _common.out_dir(None, quick=False) == _common.RESULTS


@pytest.mark.parametrize("out", ["benchmarks/results", "benchmarks/results/sub",
                                 str(BENCH / "results")])
def test_quick_into_the_tracked_results_is_refused(out, monkeypatch):
    monkeypatch.chdir(ROOT)
    with pytest.raises(SystemExit) as exc:
        _common.out_dir(out, quick=True)
    assert "refusing --out" in str(exc.value)


@pytest.mark.parametrize("script", ["bench_landing.py", "bench_integrators.py"])
def test_scripts_refuse_quick_into_results_before_measuring(script):
    before = _results_status()
    run = subprocess.run([sys.executable, str(BENCH / script), "--quick", "--out",
                          "benchmarks/results"], cwd=ROOT, capture_output=True, text=True,
                         timeout=120)
    assert run.returncode != 0 and "refusing --out" in run.stderr
    assert _results_status() == before


def test_accelerator_agreement_refuses_quick_into_results():
    target = "benchmarks/results/accelerator_agreement.json"
    before = subprocess.run(["git", "status", "--porcelain", "--", target], cwd=ROOT,
                            capture_output=True, text=True, check=True).stdout
    run = subprocess.run([sys.executable, str(BENCH / "accelerator_agreement.py"), target,
                          "--quick"], cwd=ROOT, capture_output=True, text=True, timeout=120)
    assert run.returncode == 2 and "refusing benchmarks/results/" in run.stderr, run.stderr
    assert subprocess.run(["git", "status", "--porcelain", "--", target], cwd=ROOT,
                          capture_output=True, text=True, check=True).stdout == before


@pytest.mark.parametrize("change,what", [({"quick": True}, "--quick smoke run"),
                                         ({"platform": "cpu"}, "not a GPU")])
def test_docs_tables_refuse_smoke_and_cpu_runs_under_gpu_columns(tmp_path, monkeypatch,
                                                                 change, what):
    import docs_tables

    name = "accelerator_agreement.json"
    data = json.loads((_common.RESULTS / name).read_text())
    monkeypatch.setattr(docs_tables, "RESULTS", tmp_path)
    monkeypatch.setattr(docs_tables, "ROOT", tmp_path.parent)
    (tmp_path / name).write_text(json.dumps(data))
    assert docs_tables.accelerator_agreement()  # the committed run renders
    (tmp_path / name).write_text(json.dumps({**data, **change}))
    for table in (docs_tables.accelerator_agreement, docs_tables.accelerator_samples):
        with pytest.raises(SystemExit, match=what):
            table()


def test_bench_landing_quick_writes_json_and_plot(tmp_path):
    before = _results_status()
    run = subprocess.run([sys.executable, str(BENCH / "bench_landing.py"), "--quick", "--out",
                          str(tmp_path)], cwd=ROOT, capture_output=True, text=True, timeout=600)
    assert run.returncode == 0, run.stderr
    data = json.loads((tmp_path / "bench_landing.json").read_text())
    assert data["quick"] and data["single"]["run_s"] > 0 and data["batched"][-1]["batch"] == 10
    assert (tmp_path / "bench_landing.png").read_bytes().startswith(b"\x89PNG")
    assert _results_status() == before
    # Both models' time loops compile into one native kernel, single and batched: a loop run
    # kernel by kernel (a matrix product or a scatter in the step) dispatches once per step or
    # more, which XLA:CPU's trace counts (a count, not a timing).
    for model, runs in data["per_landing_step"]["models"].items():
        for r in runs:
            assert r["dispatches_per_step"] < 0.1, (model, r["batch"], r["dispatches_per_step"])
            assert r["loop_body"]["dots"] == 0, (model, r["batch"])


def test_bench_landing_accelerator_refused_on_cpu_and_quick_runs(tmp_path):
    """``--accelerator`` measures a GPU: on a CPU backend it is refused before any work, and
    its smoke run writes the comparison with each loop's kernel count."""
    before = _results_status()
    refused = subprocess.run([sys.executable, str(BENCH / "bench_landing.py"), "--accelerator",
                              "--out", str(tmp_path / "full")], cwd=ROOT, capture_output=True,
                             text=True, timeout=120)
    assert refused.returncode == 2 and "backend here is the CPU" in refused.stderr
    assert not (tmp_path / "full").exists()
    run = subprocess.run([sys.executable, str(BENCH / "bench_landing.py"), "--accelerator",
                          "--quick", "--out", str(tmp_path)], cwd=ROOT, capture_output=True,
                         text=True, timeout=300)
    assert run.returncode == 0, run.stderr
    data = json.loads((tmp_path / "bench_landing_accelerator.json").read_text())
    for model, runs in data["per_landing_step"]["models"].items():
        for r in runs:
            body = r["loop_body"]
            assert body["kernels"] == body["fusions"] + body["copies"] + body["custom_calls"]
            assert body["kernels"] > 0 and r["us_per_step"] > 0, (model, r["batch"])
    assert (tmp_path / "bench_landing_accelerator.png").read_bytes().startswith(b"\x89PNG")
    assert _results_status() == before


def test_bench_design_gradient_modes_run_and_agree():
    """The design benchmark's forward/reverse study runs against the current DesignProblem (it
    calls internals a refactor can change) and the two modes give the same gradient."""
    import bench_design

    out = bench_design.forward_vs_reverse()
    assert out["max_rel_difference"] < 1e-9, out
    assert out["jacfwd_over_forward"] > 0 and out["grad_over_forward"] > 0


def test_every_mutation_target_is_in_the_code_once():
    """mutation_check.py plants each bug by an exact string; a refactor that rewrites the code
    leaves the mutation with nothing to plant ("target not found"), so each string is checked
    here: present exactly once under its search folders (or one of its other spellings)."""
    import mutation_check

    for m in mutation_check.MUTATIONS:
        spellings = [m.find, *(f for f, _ in m.also)]
        hits = [(s, p) for s in spellings for d in m.search
                for p in sorted((ROOT / d).rglob("*.py")) if s in p.read_text()]
        assert len(hits) == 1, (m.name, hits)
