"""Generation-quality metrics.

``bev``: feature-free BEV metrics (R2Flow protocol JSD / MMD, LiDM's occupancy
JSD and minimum matching distance). ``frechet``: the Frechet distance used by
the feature-based metrics (FRD, FRID, FSVD, FPVD, FPD). Nothing is imported
here: import the module you use, so that a stage's code hash covers only that.
"""
