"""Camera-side tracking: marker detection, per-camera and rig pose solves, the paper's method."""
