//! Sources of frames to replay: TUM folders, ROS 1 bags, ROS 2 bags (sqlite3 and MCAP), and the ROS image messages inside them.
pub mod msgs;
