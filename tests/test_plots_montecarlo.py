"""plot_montecarlo: the landings drawn and counted by how they ended (no simulation)."""

import numpy as np

import jaxland as jl
from jaxland._plots import _montecarlo as mc_plots
from jaxland._solvers import Result

# how each of the ten synthetic samples ended
CODES = [Result.SUCCESSFUL] * 5 + [Result.NONFINITE, Result.CLOSURE, Result.UNFINISHED,
                                   Result.UNFINISHED, Result.NO_TOUCHDOWN]
TIPPED = [False, True, False, True, False, False, False, True, False, False]


def synthetic_result() -> jl.MonteCarloResult:
    """Ten 3-D landings: 5 successful (2 tipped), 2 numerical failures, 2 unfinished (one
    flagged tipped as far as it ran), 1 without touchdown; the summary counts them as
    run_montecarlo does."""
    n = len(CODES)
    rng = np.random.default_rng(0)
    inputs = {"horizontal_speed_mps": np.arange(n, dtype=float),
              "roll_deg": 10.0 + np.arange(n, dtype=float)}
    outputs = {"max_stroke_m": rng.uniform(0.05, 0.1, (n, 4)),
               "peak_body_accel_mps2": rng.uniform(10, 40, n),
               "peak_strut_force_N": rng.uniform(1e4, 3e4, (n, 4)),
               "slip_distance_m": rng.uniform(0, 0.1, (n, 4)),
               "min_stability_margin_m": rng.uniform(-0.2, 0.5, n),
               "tipped_over": np.array(TIPPED)}
    prob = dict(count=2, n=5, probability=0.4, ci95_wilson=[0.1, 0.8], modelled=True,
                all_landings=dict(n=9, n_unfinished=2, n_failed=2, range=[0.333, 0.667],
                                  ci95_wilson=[0.12, 0.9]))
    summary = dict(n=n, model="full", n_succeeded=5, n_failed=2, n_unfinished=2,
                   n_no_touchdown=1, tip_over=prob, bottoming={**prob, "count": 0},
                   sensitivity=dict(target="min_stability_margin_m", ranking=[
                       {"input": "horizontal_speed_mps"}, {"input": "roll_deg"}]))
    return jl.MonteCarloResult(inputs, outputs, np.array([int(c) for c in CODES]), summary)


def test_the_tip_over_map_names_unfinished_and_untouched_landings_apart(tmp_path, monkeypatch):
    """Unfinished landings and landings without touchdown are no failures: the map marks
    each kind apart, its legend counts them as the summary does, and each marker sits on
    its own samples (they were all drawn and counted as 'failed')."""
    figs = {}
    monkeypatch.setattr(mc_plots, "_save", lambda fig, path: figs.setdefault(path.name, fig)
                        and path)  # the figures, not their pixels
    names = [p.name for p in mc_plots.plot_montecarlo(synthetic_result(), tmp_path)]
    assert names == ["mc_histograms.png", "mc_envelopes.png", "mc_tipover_map.png"]
    ax = figs["mc_tipover_map.png"].axes[0]
    labels = [t.get_text() for t in ax.get_legend().get_texts()]
    assert labels == ["stable (3)", "tipped (2)", "unfinished, no final outcome (2)",
                      "no touchdown (1)", "failed (2)"]
    drawn = {label.rsplit(" (", 1)[0]: sorted(c.get_offsets()[:, 0].tolist())
             for label, c in zip(labels, ax.collections)}
    assert drawn == {"stable": [0.0, 2.0, 4.0], "tipped": [1.0, 3.0],
                     "unfinished, no final outcome": [7.0, 8.0], "no touchdown": [9.0],
                     "failed": [5.0, 6.0]}
    counts = "10 landings: 5 successful, 2 failed, 2 unfinished, 1 without touchdown"
    assert counts in ax.get_title()
    assert "5 successful, 2 failed, 2 unfinished, 1 without touchdown;" in \
        figs["mc_histograms.png"]._suptitle.get_text()
    # each probability with where it lies over all landings (over the successful ones it is
    # biased): the title showed the biased number alone
    assert ("P(tip-over) = 0.4 [0.1, 0.8]; with the 2 unfinished and 2 failed: 0.333 to 0.667 "
            "(95% CI [0.12, 0.9])") in figs["mc_histograms.png"]._suptitle.get_text()
    hist = figs["mc_histograms.png"].axes[0]
    assert sum(p.get_height() for p in hist.patches) == 5  # the successful landings only
