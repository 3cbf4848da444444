"""Estimators: PairVis, bundle adjustment, sliding window, keyframes, robot-prior Kalman filter."""
