"""Evaluation throughput: `evaluate` reading the next batch ahead (the default) beside
reading it in turn, in one process, on the same objects.

    python experiments/benchmarks/bench_evaluate.py --workdir=assets/blocks_model --data=DIR \
        --objects=384 --out=experiments/results/bench_evaluate.json

A first evaluation of one batch compiles (and fills JAX's persistent cache, which the
timed ones then load); the two timed ones run the preset's evaluation settings (fit,
depth fit, refinement, baselines) on the same `--objects` test objects. Prints seconds,
where they went (`results["seconds_by_part"]`) and the ratio.
"""

import json
import os
import sys
import time

import jax
from absl import app, flags

from ppdjax.eval import evaluation
from ppdjax.training import checkpoints

_WORKDIR = flags.DEFINE_string("workdir", "assets/blocks_model", "The model.")
_DATA = flags.DEFINE_string("data", None, "Dataset directory.", required=True)
_OBJECTS = flags.DEFINE_integer("objects", 384, "Test objects per timed evaluation.")
_OUT = flags.DEFINE_string("out", "", "JSON path for the figures (optional).")


def main(argv):
  del argv
  if not jax.config.jax_compilation_cache_dir:
    jax.config.update("jax_compilation_cache_dir", os.path.expanduser("~/.cache/ppdjax-jax"))
  trained = checkpoints.load(_WORKDIR.value)
  settings = evaluation.eval_settings(trained[1])
  kw = dict(settings=settings, split="test", progress=False)
  t = time.perf_counter()
  evaluation.evaluate(trained, _DATA.value, max_objects=settings.batch_size, **kw)
  print(f"warm-up (compiles): {time.perf_counter() - t:.0f} s", flush=True)
  rows = {}
  for name, prefetch in (("read in turn", False), ("read ahead (default)", True)):
    r = evaluation.evaluate(trained, _DATA.value, max_objects=_OBJECTS.value,
                            prefetch=prefetch, **kw)
    rows[name] = {"seconds": r["seconds"], "objects": r["objects"],
                  "objects_per_s": r["objects"] / r["seconds"],
                  "seconds_by_part": r["seconds_by_part"]}
    print(f"{name}: {r['seconds']:.1f} s for {r['objects']} objects "
          f"({rows[name]['objects_per_s']:.2f} objects/s); {r['seconds_by_part']}", flush=True)
  ratio = rows["read in turn"]["seconds"] / rows["read ahead (default)"]["seconds"]
  print(f"read ahead: {ratio:.2f}x the objects/s of reading in turn")
  if _OUT.value:
    dev = jax.devices()[0]
    with open(_OUT.value, "w") as f:
      json.dump({"command": ("python experiments/benchmarks/bench_evaluate.py "
                             + " ".join(sys.argv[1:])),
                 "device": f"{jax.device_count()} x {dev.device_kind}", "settings": settings,
                 "rows": rows, "speedup": ratio}, f, indent=1)


if __name__ == "__main__":
  app.run(main)
