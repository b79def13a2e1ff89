"""Generation-quality metrics.

``bev``: feature-free BEV metrics (R2Flow protocol JSD / MMD, LiDM's occupancy
JSD and minimum matching distance). ``frechet``: the Frechet distance used by
the feature-based metrics (FRD, FRID, FSVD, FPVD, FPD).
"""

from omnilidar.metrics.bev import (
    LIDM_GRIDS,
    MMD_REPORT_SCALE,
    BevScores,
    LidmGrid,
    bev_histogram,
    bev_histograms,
    bev_jsd,
    bev_mmd,
    bev_scores,
    bev_scores_from_histograms,
    js_distance,
    lidm_bev_occupancies,
    lidm_bev_occupancy,
    lidm_jsd,
    lidm_mmd,
    lidm_occupancy_sum,
    mmd_in_report_units,
    protocol_subset,
)
from omnilidar.metrics.frechet import (
    feature_statistics,
    frechet_distance,
    frechet_from_features,
    trace_sqrt_product,
)

__all__ = [
    "LIDM_GRIDS",
    "MMD_REPORT_SCALE",
    "BevScores",
    "LidmGrid",
    "bev_histogram",
    "bev_histograms",
    "bev_jsd",
    "bev_mmd",
    "bev_scores",
    "bev_scores_from_histograms",
    "js_distance",
    "lidm_bev_occupancies",
    "lidm_bev_occupancy",
    "lidm_jsd",
    "lidm_mmd",
    "lidm_occupancy_sum",
    "mmd_in_report_units",
    "protocol_subset",
    "feature_statistics",
    "frechet_distance",
    "frechet_from_features",
    "trace_sqrt_product",
]
