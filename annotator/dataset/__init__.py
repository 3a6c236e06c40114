"""From a campaign (site, runs, stationary recordings) to a published dataset folder:
``campaign`` (CAMPAIGN.yaml), ``runs`` (annotation on Dask, cached by content), ``layout`` (the
published files), ``datasheet`` (README.md) and ``build`` (the whole build)."""
