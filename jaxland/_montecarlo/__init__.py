"""Monte Carlo over touchdown dispersions: sampled scenes, the smallest adequate model, chunked
``vmap`` sharded over every local device, failed samples recorded (never a crash of the batch),
tip-over (3-D model: the quarter model cannot tip) and bottoming probabilities with Wilson
intervals, envelopes and sensitivities.

Reproducibility: sample i's inputs depend only on (seed, i, input name), via
``fold_in(fold_in(key(seed), i), crc32(name))``, so the same seed gives the same samples for any
chunk size and any number of devices (and adding an input does not change the others' draws).

Scale-out: the batch axis of each chunk is sharded with ``jax.sharding.NamedSharding`` over a
1-D mesh of the process's local devices. A chunk's time loop is one single-threaded kernel, so
on a CPU the cores are used through devices: ``jax.config.update("jax_num_cpu_devices", K)``
before any JAX work (``jaxland montecarlo`` sets one per core) makes K devices of the host's
cores; on a GPU or TPU host the same code uses its accelerators. Across processes or
machines, start every process with ``init_distributed`` (JAX's multi-controller runtime; CPU
collectives over gloo) and run the same program: process p runs chunks p, p + P, ... and the
results are gathered with ``multihost_utils.process_allgather``, identical to one process's.
"""

from ._run import (
    MonteCarloResult as MonteCarloResult,
    init_distributed as init_distributed,
    run_montecarlo as run_montecarlo,
)
from ._sample import sample_scenes as sample_scenes
from ._spec import (
    DISPERSIBLE as DISPERSIBLE,
    MODEL_CHOICE as MODEL_CHOICE,
    Distribution as Distribution,
    MonteCarloSpec as MonteCarloSpec,
    envelope as envelope,
    load_montecarlo_spec as load_montecarlo_spec,
    montecarlo_spec_from_dict as montecarlo_spec_from_dict,
)
from ._stats import (
    percentiles as percentiles,
    probability_text as probability_text,
    proportion as proportion,
    sensitivity as sensitivity,
    wilson_interval as wilson_interval,
)
