"""Launch ecm-lcd beside a tracker. Not run with `ros2 launch` here (no ROS 2 installation on the build
machine); src/cli/launch_file.rs checks that its command line, at the defaults below, is one `ecm-lcd node` accepts.

    ros2 launch ecm_lcd.launch.py keyframe_topic:=/orb_slam3/keyframes params:=config/ecm_lcd.yaml
    ros2 launch ecm_lcd.launch.py input:=image image_topic:=/camera/color/image_raw input_qos:=sensor-data

input picks the frames the node reads: keyframes (a tracker's, the default), image (a camera's raw
frames; the node selects keyframes) or compressed (image_topic + "/compressed"). One only: a tracker's
keyframes and the camera's frames are the same frames numbered twice, and a raw and a compressed
stream of one camera the same frames twice. camera_info (intrinsics: verification) and depth
(registered to colour: metric poses) default to a RealSense driver's topics; a topic nobody publishes
costs nothing.
"""
from launch import LaunchDescription
from launch.actions import DeclareLaunchArgument, ExecuteProcess
from launch.substitutions import LaunchConfiguration


def generate_launch_description():
    image_topic = LaunchConfiguration("image_topic")
    keyframe_topic = LaunchConfiguration("keyframe_topic")
    camera_info_topic = LaunchConfiguration("camera_info_topic")
    depth_topic = LaunchConfiguration("depth_topic")
    params = LaunchConfiguration("params")
    input_qos = LaunchConfiguration("input_qos")
    frame_input = LaunchConfiguration("input")
    return LaunchDescription([
        DeclareLaunchArgument("image_topic", default_value="/camera/color/image_raw"),
        DeclareLaunchArgument("keyframe_topic", default_value="/tracker/keyframes"),
        DeclareLaunchArgument("camera_info_topic", default_value="/camera/color/camera_info"),
        DeclareLaunchArgument("depth_topic", default_value="/camera/aligned_depth_to_color/image_raw"),
        DeclareLaunchArgument("params", default_value="config/ecm_lcd.yaml"),
        DeclareLaunchArgument("input", default_value="keyframes",
                              description="keyframes (a tracker's) | image | compressed (a camera's)"),
        DeclareLaunchArgument("input_qos", default_value="reliable",
                              description="reliable (trackers) | sensor-data (best-effort camera drivers)"),
        # ecm-lcd is a plain binary, not an ament package, so it starts as a process with --ros-args.
        ExecuteProcess(
            cmd=["ecm-lcd", "node", "--input", frame_input, "--input-qos", input_qos, "--ros-args",
                 "-r", "__node:=ecm_lcd",
                 "--params-file", params,
                 "-r", ["image:=", image_topic],
                 "-r", ["image/compressed:=", image_topic, "/compressed"],
                 "-r", ["keyframes:=", keyframe_topic],
                 "-r", ["camera_info:=", camera_info_topic],
                 "-r", ["depth:=", depth_topic]],
            output="screen",
        ),
    ])
