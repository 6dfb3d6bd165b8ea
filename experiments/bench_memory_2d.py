"""Peak memory per particle of a 2D model, the figure the command line's size checks use
(``jaxrkpm.thesis.studies.interface.BYTES_PER_PARTICLE_2D``): the growth of this process's peak
resident memory while building the planar tracking square of ``n`` x ``n`` particles, solving
it once and taking the control point Jacobian (compiles included), per particle.

    python -m experiments.bench_memory_2d 65       # one size per process (a peak only grows)
"""
import argparse
import resource

import jax.numpy as jnp
import numpy as np

from experiments import records
from jaxrkpm.thesis.studies.track import planar_model

ap = argparse.ArgumentParser()
ap.add_argument("n", type=int, nargs="?", default=65, help="particles per side")
records.add_arguments(ap)
a = ap.parse_args()
run = records.start("bench_memory_2d", a)
n = a.n
before = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
m = planar_model(n)
sol = m.solve({"paddle": jnp.array([0.01, 0.01])})
J = m.jacobian(sol, "paddle", np.array([[0.5, 0.5]]))
after = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
print(f"{n} x {n} = {n * n} particles, {m.linear.name} solver: peak RSS {before / 1024:.0f} -> {after / 1024:.0f} MiB, "
      f"{(after - before) * 1024 / (n * n) / 1e3:.0f} kB per particle")
records.finish(run, {"n": n, "particles": n * n, "solver": m.linear.name, "peak_rss_before_mib": before / 1024,
                     "peak_rss_after_mib": after / 1024, "kb_per_particle": (after - before) * 1024 / (n * n) / 1e3})
