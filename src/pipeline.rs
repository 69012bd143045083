//! The whole per-frame path: image -> tensor -> descriptor -> keyframe selection -> detector -> loop candidates. Used by the offline commands and the ROS node alike.
