"""Learner memory per published weights version: does handing weights to the rollout workers leak?

    python -m benchmarks.weights_memory                    # 20,000 versions per path
    python -m benchmarks.weights_memory --versions 5000 --no-append

The learner publishes a new version after every iteration (~30,000 an hour on 2 cores), so a few hundred
bytes kept per version show up in a one-hour soak. This publishes ``--versions`` versions of a Table 1
model's weights without training, in one process, through two paths, and reports the learner's resident
memory growth per version:

- ``RaySampler.publish``: the project's path (the ``WeightsStore`` actor holds the weights as values);
- ``borrowed ObjectRef``: the earlier path, kept here as the reference: ``ray.put`` the weights and hand
  the actor their ObjectRef inside a list (a borrowed reference, whose bookkeeping stays with the owner).

Each path first publishes ``--warmup`` versions, so that allocator pools and Ray's first-use buffers are
full before the measured stretch. Appended to benchmarks/RESULTS.md with the command, commit and machine.
"""
from __future__ import annotations

import argparse
import datetime
import time
from typing import Callable, Dict, Sequence

from benchmarks.common import load_average, publish, section_header


def rss_mb() -> float:
    """Resident memory of this process, MiB: the learner's own metric ``system/rss_mb`` (Linux)."""
    from swarm_appo.metrics import system_metrics

    return system_metrics()["system/rss_mb"]


def growth_per_version(publish_one: Callable[[int], None], versions: int, warmup: int) -> Dict[str, float]:
    """RSS before and after ``versions`` calls of ``publish_one(version)`` (after ``warmup`` calls), and the
    growth per call in bytes."""
    for v in range(warmup):
        publish_one(v)
    before, t0 = rss_mb(), time.perf_counter()
    for v in range(warmup, warmup + versions):
        publish_one(v)
    after = rss_mb()
    return {"rss_before_mb": before, "rss_after_mb": after,
            "bytes_per_version": (after - before) * 2**20 / versions,
            "ms_per_version": 1e3 * (time.perf_counter() - t0) / versions}


def main(argv: Sequence[str] = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--versions", type=int, default=20000)
    p.add_argument("--warmup", type=int, default=2000)
    p.add_argument("--config", default="configs/table1/recipe.yaml", help="the config whose model is published")
    p.add_argument("--no-append", action="store_true")
    args = p.parse_args(argv)
    if args.versions < 1 or args.warmup < 0:
        p.error("--versions must be >= 1 and --warmup >= 0")

    import ray

    from swarm_appo.config import ConfigError, load_config
    from swarm_appo.model import model_factory
    from swarm_appo.ray_sampling import RaySampler, WeightsStore, init_local_ray

    try:
        cfg = load_config(args.config, [])
    except ConfigError as exc:
        p.error(f"--config: {exc}")
    make_model = model_factory(cfg.env.obs_layout(), cfg.model)
    state_dict = make_model().state_dict()
    nbytes = sum(t.numel() * t.element_size() for t in state_dict.values())
    started, load_before = datetime.datetime.now().isoformat(timespec="seconds"), load_average()
    init_local_ray(2)
    try:
        # one worker, never asked for a fragment: only the publish path runs
        sampler = RaySampler(cfg.env, make_model, num_workers=1, envs_per_worker=1, rollout=8, seed=0,
                             max_in_flight=1)
        project = growth_per_version(lambda v: sampler.publish(v, state_dict), args.versions, args.warmup)
        sampler.close()
        store = WeightsStore.remote()

        def borrowed(v: int) -> None:
            ref = ray.put((v, state_dict, None))
            ray.get(store.set.remote(v, [ref], None))  # the earlier path: the ref inside a list stays unresolved

        reference = growth_per_version(borrowed, args.versions, args.warmup)
        ray.kill(store)
    finally:
        ray.shutdown()

    rows = []
    for name, m in (("`RaySampler.publish` (weights held as values)", project),
                    ("borrowed ObjectRef in a list (the earlier path)", reference)):
        rows.append(f"| {name} | {m['rss_before_mb']:.1f} | {m['rss_after_mb']:.1f} | "
                    f"{m['bytes_per_version']:.0f} | {m['ms_per_version']:.2f} |")
        print(rows[-1], flush=True)
    section = "\n".join([
        *section_header("weights_memory", started, argv, ["swarm_appo"], load_before),
        f"- weights of `{args.config}`'s model ({nbytes / 1024:.0f} KiB), {args.versions:,} versions per path after "
        f"{args.warmup:,} warm-up versions, one process, no training; learner RSS as `system/rss_mb` reads it",
        "", "| path | RSS before (MiB) | RSS after (MiB) | growth per version (bytes) | ms per version |",
        "|---|---:|---:|---:|---:|", *rows])
    publish(section, not args.no_append)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
