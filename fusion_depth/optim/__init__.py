"""Optimisation: learning-rate schedules, created by name (``scheduler=``)."""
