"""Built-in OOD detectors (SPEC §5), registered by name and imported on first use.

Score direction, for every detector: a larger score means more anomalous. This module imports
nothing heavy: each detector's module loads only when the registry is asked for it. Plugins
register through the `oodrl.detectors` entry-point group.

Besides its own parameters (see each class), every detector takes `threshold_rule`
("percentile", "max" = the largest held-out score, or "episode_max" = a conformal bound α on
the probability of any false alarm in a clean trajectory; default "percentile", `pedm` "max";
see `oodrl.core.detector`), `threshold_percentile` (default 99.0), `alpha` (default 0.05) and
`seed` (default 0; weights, data order, subsamples). `detector.stream()` scores step by step
(`oodrl.core.stream`).
"""

from oodrl.registry import Registry

# A params `class:` naming a PyOD, scikit-learn or river class gets it wrapped (SPEC §17).
DETECTORS = Registry("detector", adapt="oodrl.detectors.library:as_detector")

DETECTORS.register("mahalanobis_distance", "oodrl.detectors.mahalanobis:MahalanobisDistance")
DETECTORS.register("time_series_features", "oodrl.detectors.time_series:TimeSeriesFeatures")
DETECTORS.register("pedm", "oodrl.detectors.pedm:Pedm")
DETECTORS.register("autoencoder", "oodrl.detectors.autoencoder:Autoencoder")
DETECTORS.register("ensemble_disagreement", "oodrl.detectors.ensemble:EnsembleDisagreement")
DETECTORS.register("cusum", "oodrl.detectors.cusum:Cusum")
DETECTORS.register("kde_density", "oodrl.detectors.kde:KdeDensity")
DETECTORS.register("lyapunov_divergence", "oodrl.detectors.lyapunov:LyapunovDivergence")
DETECTORS.register("q_margin", "oodrl.detectors.policy_view:QMargin")
DETECTORS.register("q_entropy", "oodrl.detectors.policy_view:QEntropy")
DETECTORS.register("q_energy", "oodrl.detectors.policy_view:QEnergy")
DETECTORS.register("max_softmax", "oodrl.detectors.policy_view:MaxSoftmax")
DETECTORS.register("fqe_td", "oodrl.detectors.fqe:FqeTd")
DETECTORS.register("conformal_martingale", "oodrl.detectors.martingale:ConformalMartingale")
DETECTORS.register("deedee", "oodrl.detectors.deedee:Deedee")
DETECTORS.register("random_scores", "oodrl.detectors.random_scores:RandomScores")
DETECTORS.register("riqn", "oodrl.detectors.riqn:Riqn")
# Sequential baselines of SPEC §24 (protocol 4).
DETECTORS.register("cusum_tv", "oodrl.detectors.cusum_tv:CusumTV")
DETECTORS.register("action_consistency", "oodrl.detectors.action_consistency:ActionConsistency")

__all__ = ["DETECTORS"]
