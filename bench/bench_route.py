"""Route assessment: what a sample costs, read on the map and judged for the envelope.

On the isolation bench's ``heavy`` region (4 x 4 x 0.6 km, 21 x 21 x 7 hinges, 30,000
observations of eight headings), with one class and with 8 sectors: the CPU time per
sample of :func:`bdf.region.route.assess` reading the map (a chunk of
:data:`~bdf.region.route.CHUNK_SAMPLES` samples, the mode flown, its share and mean) and of
:func:`~bdf.region.route.envelope` (a vehicle turning on a coin: samples every metre), best
of ``--repeat``, side by side in one run; their ratio is what
:data:`~bdf.region.route.ENVELOPE_SAMPLES_PER_POINT` is set from (the service costs a route
as its map samples plus its envelope samples over that).

    python bench/bench_route.py [--repeat 5] [--no-append]
"""

from __future__ import annotations

import datetime
import platform
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from bench_core import arguments, publish, rows_table  # bench/ is on the path

from bdf.region import route
from bdf.region.evidence import increments, region_total
from bdf.region.map import RegionMap, compute_posterior
from bdf.region.spec import RegionSpec
from tests.service.test_isolation import HEAVY, traffic


def per_sample(fn, samples: int, repeat: int) -> float:
    """Best CPU seconds per sample of ``fn()`` over ``repeat`` runs."""
    best = np.inf
    for _ in range(repeat):
        t0 = time.process_time()
        fn()
        best = min(best, time.process_time() - t0)
    return best / samples


def main() -> None:
    parser = arguments(__doc__)
    parser.add_argument("--repeat", type=int, default=5)
    args = parser.parse_args()
    X, V = traffic(30000, 1)
    coin = route.Vehicle(60.0, 0.01, 8.0, 8.0, 0.0, 600.0)
    legs = 40  # 160 km of zig-zag: 16,000 map samples, 160,000 of the envelope
    P = np.array([[4000.0 * (i % 2), 4000.0 * i / legs, 300.0] for i in range(legs + 1)])
    on_map, on_envelope = route.samples(P, coin)
    rows = []
    for directions in (1, 8):
        spec = RegionSpec.model_validate({**HEAVY, "directions": directions})
        evidence = region_total(spec, {k: i.evidence for k, i in increments(spec, X, V).items()})
        rmap = RegionMap(spec, compute_posterior(spec, evidence))
        delta = np.diff(P, axis=0)
        seg = np.repeat(np.arange(legs), on_map // legs)
        within = (np.arange(len(seg)) % (on_map // legs) + 0.5) / (on_map // legs)
        Q, velocity = P[seg] + within[:, None] * delta[seg], delta[seg] / 66.7
        heading = np.degrees(np.arctan2(velocity[:, 0], velocity[:, 1])) % 360

        def read(Q=Q, velocity=velocity, heading=heading, rmap=rmap):
            for lo in range(0, len(Q), route.CHUNK_SAMPLES):
                part = slice(lo, lo + route.CHUNK_SAMPLES)
                route._read(rmap, Q[part], velocity[part], heading[part])

        map_s = per_sample(read, len(Q), args.repeat)
        envelope_s = per_sample(lambda: route.envelope(P, coin), on_envelope, args.repeat)
        rows.append(
            {
                "sectors": directions,
                "map sample [us]": round(map_s * 1e6, 2),
                "envelope sample [us]": round(envelope_s * 1e6, 3),
                "map / envelope": round(map_s / envelope_s, 1),
            }
        )
        print(rows[-1], flush=True)
    report = [
        f"\n## Route assessment, {datetime.date.today().isoformat()}\n",
        f"`python bench/bench_route.py --repeat {args.repeat}` on {platform.node()} (CPU time per "
        f"sample, best of {args.repeat}; a 160 km zig-zag: {on_map} map samples, {on_envelope} "
        f"envelope samples of a vehicle turning on a coin; `ENVELOPE_SAMPLES_PER_POINT` = "
        f"{route.ENVELOPE_SAMPLES_PER_POINT})\n",
        rows_table(rows),
    ]
    publish(report, not args.no_append)


if __name__ == "__main__":
    main()
