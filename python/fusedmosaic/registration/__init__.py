"""Image registration: features + RANSAC homographies (seed 000), NCC (seed 004), pair selection."""
