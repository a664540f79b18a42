"""Camera ego-motion from events: rotation by contrast maximisation, 6-DoF pose by map alignment."""

MODES = ("off", "rotation", "6dof")  # what the tracker service estimates of the camera's motion (`etam tracker --ego`)
ODOMETRY_MODES = ("rotation", "6dof")  # what `etam odom --mode` estimates offline
