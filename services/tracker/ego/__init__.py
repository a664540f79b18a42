"""Camera ego-motion from events: rotation by contrast maximisation, 6-DoF pose by map alignment."""

MODES = ("off", "rotation", "6dof")  # what the tracker service estimates of the camera's motion (`etam tracker --ego`)
ODOMETRY_MODES = ("rotation", "6dof")  # what `etam odom --mode` estimates offline
# a stereo loop's keyframes asked for at this share of its best inlier share (`loop.RefreshParams`; dev rigs 1-6:
# mean 0.94 % ATE, 1.08 never asked for, 1.58 at 0.8: keyframes made as the pose weakens carry its error into the map)
STEREO_WEAK_SHARE = 0.6
