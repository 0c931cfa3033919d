"""Spinopelvic measurement: parameters from landmark sets, the GAP score, parameter tables."""
