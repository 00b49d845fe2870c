"""Navigation with a calibration: strapdown free-inertial integration (``strapdown``), stationary alignment
(``alignment``), and the error budget a record buys (``budget``: alignment and drift, calibrated vs uncalibrated,
with an HTML fragment for the certificate)."""

from assets_lib.navigation.budget import budget_html, navigation_budget

__all__ = ["budget_html", "navigation_budget"]
