"""Camera ego-motion from events: angular velocity by contrast maximisation, integrated to orientation."""

MODES = ("off", "rotation")  # what the tracker service estimates of the camera's motion (`etam tracker --ego`)
