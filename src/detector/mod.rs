//! Keyframe database and loop-closure detector: which earlier keyframe, if any, does a new one revisit.
