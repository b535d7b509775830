"""``magmesh train dmc``: train the fuzzy c-means centres of the ``fcm`` DMC detector.

Simulates the training drive(s) with the car simulator (seeded), computes the DMC features with the
car's static compensation, fits FCM (c = 5, m' = 2, ε = 0.01) on the samples that pass the loose
stage-1 thresholds, orders the clusters (by the drive's true heading error, or by centre size with
``--paper-order``) and writes a versioned JSON model (default ``models/dmc_fcm_v1.json``, which the
``fcm`` service loads). Train on one drive, apply to the others (the paper's Table 4).
"""

from __future__ import annotations

import argparse
import json
import sys


def register(subparsers) -> None:
    p = subparsers.add_parser("train", help="train offline models (dmc: FCM centres of the fcm DMC detector)",
                              description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = p.add_subparsers(dest="what", required=True, metavar="MODEL")
    d = sub.add_parser("dmc", help="FCM centres for the fcm implementation of dmc_detector",
                       description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    add_arguments(d)
    d.set_defaults(func=run)


def add_arguments(p: argparse.ArgumentParser) -> None:
    from bench import dmc_training as T

    default_drives = ",".join(f"{lay}:{seed}" for lay, seed in T.DEFAULT_TRAIN_DRIVES)
    p.add_argument("--drives", default=default_drives,
                   help=f"training drives as layout:seed[,layout:seed...] (default {default_drives})")
    p.add_argument("--duration-s", type=float, default=300.0, help="length of each simulated drive, s")
    p.add_argument("--features", choices=["paper", "extended"], default=T.DEFAULT_FEATURE_SET,
                   help="paper: E_m, E_h; extended: all four normalised features")
    p.add_argument("--paper-order", action="store_true",
                   help="order clusters by centre size and sum the two smallest (no reference heading used)")
    p.add_argument("--clusters", type=int, default=5, help="c, number of clusters")
    p.add_argument("--seed", type=int, default=0, help="seed of the initial memberships")
    p.add_argument("--kc-min", type=float, default=0.8, help="valid when K_c > this")
    p.add_argument("-o", "--output", default=None, help="model file (default models/dmc_fcm_v1.json)")
    p.add_argument("--json", action="store_true", help="print the model as JSON instead of a summary")


def parse_drives(text: str) -> list[tuple[str, int]]:
    out = []
    for part in text.split(","):
        lay, sep, seed = part.strip().partition(":")
        if not sep:
            raise SystemExit(f"--drives: {part!r} is not layout:seed")
        out.append((lay, int(seed)))
    return out


def run(args: argparse.Namespace) -> int:
    from bench import dmc_training as T
    from services.dmc_detector import fcm

    drives = [T.simulate_drive(lay, seed, args.duration_s) for lay, seed in parse_drives(args.drives)]
    model = T.train_fcm(drives, args.features, seed=args.seed, use_reference=not args.paper_order,
                        c=args.clusters, kc_min=args.kc_min)
    path = model.save(args.output or fcm.DEFAULT_MODEL)
    if args.json:
        print(json.dumps(model.to_json()))
    else:
        m = T.evaluate(T.fcm_valid(drives, model), drives)
        print(f"wrote {path}: {model.feature_set} features, {len(model.centres)} centres "
              f"({model.training['cluster_order']} order, K_c from {model.n_good_clusters}), "
              f"{model.training['n_samples']} training vectors, {model.training['n_iter']} iterations")
        for i, c in enumerate(model.centres):
            err = model.training.get("cluster_err_deg")
            print(f"  centre {i}: {[round(float(x), 4) for x in c]}" + (f"  mean error {err[i]:.2f}°" if err else ""))
        print(f"on the training drive(s): RP {m.rp_pct:.2f} %  MP {m.mp_pct:.3f} %  WP {m.wp_deg:.2f}°")
    return 0


if __name__ == "__main__":
    ap = argparse.ArgumentParser(description=__doc__)
    add_arguments(ap)
    sys.exit(run(ap.parse_args()))
