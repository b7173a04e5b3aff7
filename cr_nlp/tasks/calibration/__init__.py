"""Calibration of a robot's actuation model from a recording: the static fit (``calibrate``),
the history-aware fit (``history``, play operators of ``model.history``) and the
recording's rows (``measurements``). Units: metres, radians."""
