"""How much a calibration needs: the API checks uploads against these before a job starts. No imports, so the
API can read them without loading OpenCV."""

MIN_VIEWS = 3  # a camera (or a rig) needs boards seen from at least three directions
MIN_POINTS = 6  # per view: a pose has 6 unknowns
