//! Detector, keyframe-selection and descriptor parameters, read from a ROS 2 params file (`config/ecm_lcd.yaml`) so the node and the offline commands share one file.

use serde::{Deserialize, Serialize};

/// A parameter value as ROS 2 types it (the subset ecm-lcd uses).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(untagged)]
pub enum ParamValue {
    Bool(bool),
    Integer(i64),
    Double(f64),
    String(String),
}
