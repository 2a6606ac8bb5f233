"""Optimisation: learning-rate schedules, created by name (``scheduler=``, :mod:`.schedules`),
and the values the ``optimizer`` group may take (:mod:`.optimizers`)."""
