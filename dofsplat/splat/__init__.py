"""Per-splat projection: Jacobian, resampling kernel, DOF variance, circumellipse."""
