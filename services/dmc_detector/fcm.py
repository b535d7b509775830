"""Stage 2 of the DMC detector: fuzzy c-means (FCM) recognition and the credibility K_c (docs/methods.md#dmc-fcm).

Pure numpy; never imports zenoh.

FCM (Bezdek) minimises J_m = Σ_k Σ_i μ_ik^m' d_ik² over memberships μ (columns sum to 1) and centres v:

    v_i  = Σ_k μ_ik^m' x_k / Σ_k μ_ik^m'                                   (centre update)
    μ_ik = 1 / Σ_j (d_ik / d_jk)^(2/(m'−1))                                 (membership update)

iterated until max |μ^(r+1) − μ^(r)| < ε (the paper: c = 5, m' = 2, ε = 0.01). The implementation is
vectorised over samples and clusters and works with squared distances throughout: for m' = 2 the
membership is μ_ik ∝ 1/d_ik², no square root or power is needed.

The paper leaves open how "error size" is measured. Without a reference heading in the training data
the clusters are ordered by the distance of their centre from the origin (no disturbance) and the two
smallest make up K_c. When the training drive has a reference heading (simulation, or a recording with
a reference), :func:`train` orders the clusters by the heading error of their members and lets every
cluster whose error is small make up K_c: the improvement that holds up under calibration errors,
which spread the undisturbed features over several clusters.

Online, trained centres are reused (the paper's Table 4): memberships of each new sample follow from
the membership update alone. Clusters are ordered by error size (distance of the centre from the
origin, i.e. from "no disturbance"); the credibility of compass k is the summed membership of the two
smallest-error clusters, K_ck = U(1) + U(2) in this order (the paper's U(4, i) + U(5, i)), and the
system credibility is K_c = min(K_c1, K_c2); the heading is valid when K_c > 0.8.

Feature vectors (normalised by the loose stage-1 thresholds and clipped to [0, 1]):
``paper``     x_k = [|Δm_k| / V_Δm, |Δh| / V_Δh]                               (the paper's E_m, E_h)
``extended``  x_k = [|Δm_k| / V_Δm, |dΔm_k| / V_dΔm, |Δh| / V_Δh, |dΔh| / V_dΔh]  (all four tests)
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from magmesh.paths import MODELS_DIR

from . import core
from .core import Features, Thresholds

MODEL_FORMAT = "magmesh.dmc_fcm"
MODEL_VERSION = 1
DEFAULT_MODEL = MODELS_DIR / "dmc_fcm_v1.json"
#: centres for HMR3300 compasses at 8 Hz on the paper-streets drives (``magmesh train dmc --drives paper_a:1``)
PAPER_STREETS_MODEL = MODELS_DIR / "dmc_fcm_paper_streets_v1.json"
FEATURE_SETS = {"paper": ("dm", "dh"), "extended": ("dm", "ddm", "dh", "ddh")}
#: the paper's loosest Table 1 set (200, 100, 8, 8) with 10 nT per HMR3300 field unit: stage 1 of ``fcm``
LOOSE = Thresholds(2000.0, 1000.0, 8.0, 8.0)


# ---- fuzzy c-means ----------------------------------------------------------------------------


def _sqdist(X: np.ndarray, V: np.ndarray) -> np.ndarray:
    """Squared Euclidean distances, c×N, from centres V (c×d) to samples X (N×d)."""
    # ‖x‖² + ‖v‖² − 2 v·x, floored at a tiny positive value (a sample on a centre)
    d2 = (V * V).sum(1)[:, None] + (X * X).sum(1)[None, :] - 2.0 * (V @ X.T)
    np.maximum(d2, 1e-18, out=d2)
    return d2


def memberships(X, centres, m: float = 2.0) -> np.ndarray:
    """FCM memberships (c×N) of samples X (N×d) in fixed clusters (membership update)."""
    X = np.asarray(X, float)
    V = np.asarray(centres, float)
    d2 = _sqdist(X, V)
    if m == 2.0:
        inv = 1.0 / d2
    else:
        inv = d2 ** (-1.0 / (m - 1.0))  # (d²)^(−1/(m−1)) = d^(−2/(m−1))
    return inv / inv.sum(0, keepdims=True)


@dataclass
class FcmResult:
    centres: np.ndarray  # c×d
    u: np.ndarray  # c×N final memberships
    n_iter: int
    objective: list[float]  # J_m per iteration
    converged: bool


def fcm_fit(X, c: int = 5, m: float = 2.0, tol: float = 0.01, max_iter: int = 300, seed: int = 0,
            u0: np.ndarray | None = None) -> FcmResult:
    """Fit FCM to samples X (N×d). ``u0`` (c×N) fixes the initial memberships (else seeded random)."""
    X = np.asarray(X, float)
    if X.ndim != 2 or len(X) < c:
        raise ValueError(f"need an N×d sample array with N ≥ c = {c}, got shape {X.shape}")
    if not m > 1:
        raise ValueError(f"the fuzzifier m must be > 1, got {m}")
    if u0 is None:
        u = np.random.default_rng(seed).random((c, len(X)))
    else:
        u = np.array(u0, float, copy=True)
        if u.shape != (c, len(X)):
            raise ValueError(f"u0 must be {c}×{len(X)}, got {u.shape}")
    u /= u.sum(0, keepdims=True)
    objective = []
    converged = False
    it = 0
    for it in range(1, max_iter + 1):  # noqa: B007 (it is the iteration count returned)
        um = u * u if m == 2.0 else u**m
        V = (um @ X) / um.sum(1)[:, None]  # centre update
        d2 = _sqdist(X, V)
        objective.append(float((um * d2).sum()))
        inv = 1.0 / d2 if m == 2.0 else d2 ** (-1.0 / (m - 1.0))
        u_new = inv / inv.sum(0, keepdims=True)  # membership update
        delta = float(np.abs(u_new - u).max())
        u = u_new
        if delta < tol:
            converged = True
            break
    return FcmResult(V, u, it, objective, converged)


# ---- the trained model ------------------------------------------------------------------------


@dataclass
class FcmModel:
    """Trained FCM centres, ordered by error size, with what they need to be applied."""

    centres: np.ndarray  # c×d, row 0 = smallest error
    feature_set: str = "extended"
    loose: Thresholds = LOOSE  # stage-1 thresholds, also the features' normalisation
    m: float = 2.0
    kc_min: float = 0.8  # valid when K_c > kc_min
    n_good_clusters: int = 2  # clusters whose memberships make up K_c
    training: dict = field(default_factory=dict)  # where the centres came from
    feature_settings: core.FeatureSettings = core.FeatureSettings()  # windows the centres were trained with

    def __post_init__(self):
        self.centres = np.asarray(self.centres, float)
        if self.feature_set not in FEATURE_SETS:
            raise ValueError(f"feature_set must be one of {', '.join(FEATURE_SETS)}, got {self.feature_set!r}")
        if self.centres.ndim != 2 or self.centres.shape[1] != len(FEATURE_SETS[self.feature_set]):
            raise ValueError(f"centres must be c×{len(FEATURE_SETS[self.feature_set])} for feature set "
                             f"{self.feature_set!r}, got shape {self.centres.shape}")
        if not 1 <= self.n_good_clusters < len(self.centres):
            raise ValueError("n_good_clusters must be at least 1 and fewer than the clusters")
        if not 0 < self.kc_min < 1:
            raise ValueError(f"kc_min must be in (0, 1), got {self.kc_min}")

    # ---- features -> credibility ---------------------------------------------------------
    def compass_features(self, f: Features) -> tuple[np.ndarray, np.ndarray]:
        """Normalised feature vectors of compass 1 and 2 (each N×d, clipped to [0, 1])."""
        th = self.loose
        cols = {
            "dm": np.abs(f.dm_nt) / th.dm_nt,  # N×2
            "ddm": np.abs(f.ddm_nt_s) / th.ddm_nt_s,
            "dh": np.repeat((np.abs(np.degrees(f.dh_rad)) / th.dh_deg)[:, None], 2, axis=1),
            "ddh": np.repeat((np.abs(np.degrees(f.ddh_rad_s)) / th.ddh_deg_s)[:, None], 2, axis=1),
        }
        names = FEATURE_SETS[self.feature_set]
        x = np.clip(np.stack([cols[n] for n in names], axis=-1), 0.0, 1.0)  # N×2×d
        return x[:, 0, :], x[:, 1, :]

    def credibility(self, f: Features) -> tuple[np.ndarray, np.ndarray]:
        """(K_c, [K_c1, K_c2]) per epoch: K_ck = Σ memberships of the smallest-error clusters."""
        x1, x2 = self.compass_features(f)
        k = self.n_good_clusters
        kc1 = memberships(x1, self.centres, self.m)[:k].sum(0)
        kc2 = memberships(x2, self.centres, self.m)[:k].sum(0)
        return np.minimum(kc1, kc2), np.stack([kc1, kc2], axis=-1)

    def classify(self, f: Features) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(valid, stage1_pass, K_c) per epoch: stage 1 with the loose thresholds, then K_c > kc_min."""
        stage1 = core.threshold_test(f, self.loose)
        kc, _ = self.credibility(f)
        kc = np.where(stage1, kc, 0.0)
        return stage1 & (kc > self.kc_min), stage1, kc

    # ---- persistence ---------------------------------------------------------------------
    def to_json(self) -> dict:
        return {
            "format": MODEL_FORMAT,
            "version": MODEL_VERSION,
            "feature_set": self.feature_set,
            "features": list(FEATURE_SETS[self.feature_set]),
            "loose_thresholds": {"dm_nt": self.loose.dm_nt, "ddm_nt_s": self.loose.ddm_nt_s,
                                 "dh_deg": self.loose.dh_deg, "ddh_deg_s": self.loose.ddh_deg_s},
            "m": self.m,
            "kc_min": self.kc_min,
            "n_good_clusters": self.n_good_clusters,
            "centres": [[round(float(x), 8) for x in row] for row in self.centres],  # pragma: no mutate (storage precision: 1e-8 of features in [0, 1])
            "feature_settings": {"smooth_window_s": self.feature_settings.smooth_window_s,
                                 "rate_window_s": self.feature_settings.rate_window_s},
            "training": self.training,
        }

    @classmethod
    def from_json(cls, d: dict) -> FcmModel:
        if d.get("format") != MODEL_FORMAT:
            raise ValueError(f"not a DMC FCM model (format {d.get('format')!r}, expected {MODEL_FORMAT!r})")
        if d.get("version") != MODEL_VERSION:
            raise ValueError(f"DMC FCM model version {d.get('version')!r}; this code reads version {MODEL_VERSION}")
        lt = d["loose_thresholds"]
        return cls(np.asarray(d["centres"], float), d["feature_set"],  # pragma: no mutate (dtype: __post_init__ converts)
                   Thresholds(lt["dm_nt"], lt["ddm_nt_s"], lt["dh_deg"], lt["ddh_deg_s"]), float(d["m"]),
                   float(d["kc_min"]), int(d["n_good_clusters"]), dict(d.get("training", {})),
                   core.FeatureSettings(**d.get("feature_settings", {})))

    def save(self, path: str | Path) -> Path:
        path = Path(path)
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(json.dumps(self.to_json(), indent=1) + "\n")
        return path

    @classmethod
    def load(cls, path: str | Path = DEFAULT_MODEL) -> FcmModel:
        path = Path(path)
        try:
            return cls.from_json(json.loads(path.read_text()))
        except FileNotFoundError:
            raise FileNotFoundError(f"FCM model {path} not found: train one with `magmesh train dmc`") from None


def order_by_error(centres: np.ndarray) -> np.ndarray:
    """Centres sorted by error size (distance from the origin = no disturbance), smallest first."""
    centres = np.asarray(centres, float)  # pragma: no mutate (dtype: the norms and the ordering are the same for ints)
    return centres[np.argsort(np.linalg.norm(centres, axis=1), kind="stable")]


def train(features: list[Features], feature_set: str = "extended", loose: Thresholds | None = None, c: int = 5,
          m: float = 2.0, tol: float = 0.01, seed: int = 0, kc_min: float = 0.8,
          training_info: dict | None = None, feature_settings: core.FeatureSettings | None = None,
          heading_err_deg: list[np.ndarray] | None = None, good_cluster_deg: float = 2.0) -> FcmModel:
    """Fit centres on the stage-1 survivors (loose thresholds) of the given drives (§1 stage 2).

    Without ``heading_err_deg`` the clusters are ordered by the size of their centre (distance from
    "no disturbance") and K_c sums the two smallest, as in the paper. With the training drives' heading
    errors (a reference heading was recorded) the clusters are ordered by the membership-weighted mean
    heading error of their samples, and K_c sums every cluster whose error is below ``good_cluster_deg``
    (at least one): which clusters mean "trustworthy" is learned rather than assumed.
    """
    loose = loose or LOOSE
    probe = FcmModel(np.zeros((c, len(FEATURE_SETS[feature_set]))), feature_set, loose, m, kc_min)
    xs, es = [], []
    for i, f in enumerate(features):
        keep = core.threshold_test(f, loose) & f.rates_ready
        x1, x2 = probe.compass_features(f)
        xs += [x1[keep], x2[keep]]
        if heading_err_deg is not None:
            e = np.asarray(heading_err_deg[i], float)[keep]
            es += [e, e]
    X = np.concatenate(xs)
    res = fcm_fit(X, c=c, m=m, tol=tol, seed=seed)
    info = dict(training_info or {})
    info.update(n_samples=int(len(X)), n_iter=res.n_iter, converged=res.converged,
                objective=round(res.objective[-1], 6), c=c, tol=tol, seed=seed)
    if heading_err_deg is None:
        centres, n_good = order_by_error(res.centres), 2
        info["cluster_order"] = "centre_norm"
    else:
        E = np.concatenate(es)
        w = res.u**m
        cluster_err = (w * E[None, :]).sum(1) / w.sum(1)  # membership-weighted mean |heading error|
        order = np.argsort(cluster_err, kind="stable")
        centres = res.centres[order]
        n_good = int(np.clip((cluster_err < good_cluster_deg).sum(), 1, c - 1))
        info.update(cluster_order="heading_error", cluster_err_deg=[round(float(x), 4) for x in cluster_err[order]],
                    good_cluster_deg=good_cluster_deg)
    return FcmModel(centres, feature_set, loose, m, kc_min, n_good, info, feature_settings or core.FeatureSettings())


# ---- the streaming detector -------------------------------------------------------------------


@dataclass(frozen=True)
class FcmDetectorSettings:
    hysteresis: core.HysteresisSettings = core.HysteresisSettings()
    kc_min: float | None = None  # None: the model's
    dh_ref_rad: float = 0.0


class FcmDetector(core.ThresholdDetector):
    """Stage 1 with the model's loose thresholds, then K_c from the trained centres."""

    impl = "fcm"

    def __init__(self, model: FcmModel, settings: FcmDetectorSettings | None = None):
        s = settings or FcmDetectorSettings()
        self.model = model
        self.kc_min = float(s.kc_min if s.kc_min is not None else model.kc_min)
        fs = model.feature_settings
        features = core.FeatureSettings(fs.smooth_window_s, fs.rate_window_s, s.dh_ref_rad, fs.max_gap_s)
        super().__init__(core.ThresholdDetectorSettings(model.loose, features, s.hysteresis))

    def update(self, t_s: float, b1_nt, b2_nt, p1, p2, declination_rad: float = 0.0) -> core.Decision:
        f = self.tracker.update(t_s, b1_nt, b2_nt, p1, p2, declination_rad)
        stage1, ratios, failed = self._decide(f, self.model.loose)
        kc_arr, _ = self.model.credibility(f)
        kc = float(kc_arr[0]) if stage1 else 0.0
        ratios["kc"] = kc
        valid = stage1 and kc > self.kc_min
        if stage1 and not valid:
            failed = ("kc",)
        return self._finish(f, stage1, kc, valid, ratios, failed)

    def describe(self, d: core.Decision) -> tuple[str, float | None, float | None, str]:
        if d.transition == "raised" and d.failed == ("kc",):
            return (f"Magnetic interference suspected: credibility K_c {d.credibility:.2f} is not above "
                    f"{self.kc_min:.2f} (fuzzy c-means on the DMC features).", d.credibility, self.kc_min, "")
        return super().describe(d)
