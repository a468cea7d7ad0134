"""Prediction without DEM: one transport law fitted jointly to a library of DEM runs
(:mod:`workflows.prediction.library`), and the operating point it never ran predicted
with an interval checked on runs left out (:mod:`workflows.prediction.predict`)."""
