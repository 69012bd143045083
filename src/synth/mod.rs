//! Synthetic indoor sequences with loops and exact ground truth, rendered by the project itself.
