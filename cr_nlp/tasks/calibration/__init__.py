"""Calibration of a robot's models from a recording of motor commands and tip positions:
the static geometric (PCC) fit (``calibrate``), the history-aware fit (``history``, play
operators of ``model.history``), the Cosserat rod driven by the commands (``mechanics``,
``cr-nlp calibrate --model cosserat``) and the recording's rows (``measurements``).
Units: metres, radians, newtons."""
