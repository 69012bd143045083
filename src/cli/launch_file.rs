//! Test: `launch_notes/ecm_lcd.launch.py` matches the code: the command it starts, with its launch
//! arguments at their defaults, parses as `ecm-lcd node` does (options, `--ros-args`), its remaps name
//! each of the node's input topics, and its default params file is `config/ecm_lcd.yaml`, which loads to the
//! built-in defaults. The launch file is read with Python's `ast` (no ROS 2 needed): substitutions are
//! replaced by the declared defaults, as `ros2 launch` does without overrides.

use std::path::Path;
use std::process::Command;

use super::{Cli, Command as EcmCommand};
use clap::Parser;
use ecm_lcd::config::Params;
use ecm_lcd::ros::args::RosArgs;
use ecm_lcd::ros::node::{
    CAMERA_INFO_TOPIC, COMPRESSED_TOPIC, DEFAULT_NODE_NAME, DEPTH_TOPIC, IMAGE_TOPIC, KEYFRAMES_TOPIC,
};

/// The `cmd` of the launch file's ExecuteProcess with every LaunchConfiguration replaced by its
/// DeclareLaunchArgument default and list elements joined (launch concatenates them).
const EXTRACT: &str = r#"
import ast, json, sys
tree = ast.parse(open(sys.argv[1]).read())
names, defaults, cmd = {}, {}, None
for node in ast.walk(tree):
    if isinstance(node, ast.Assign) and isinstance(node.value, ast.Call) \
            and getattr(node.value.func, "id", "") == "LaunchConfiguration":
        names[node.targets[0].id] = node.value.args[0].value
    if isinstance(node, ast.Call) and getattr(node.func, "id", "") == "DeclareLaunchArgument":
        kw = {k.arg: k.value for k in node.keywords}
        defaults[node.args[0].value] = kw["default_value"].value
    if isinstance(node, ast.Call) and getattr(node.func, "id", "") == "ExecuteProcess":
        cmd = next(k.value for k in node.keywords if k.arg == "cmd")
def value(element):
    if isinstance(element, ast.Constant):
        return element.value
    if isinstance(element, ast.Name):
        return defaults[names[element.id]]
    if isinstance(element, ast.List):
        return "".join(value(e) for e in element.elts)
    raise SystemExit(f"unexpected element {ast.dump(element)}")
print(json.dumps([value(e) for e in cmd.elts]))
"#;

#[test]
fn the_launch_file_starts_the_node_the_code_defines() {
    let root = Path::new(env!("CARGO_MANIFEST_DIR"));
    let out = Command::new("python3")
        .args(["-c", EXTRACT])
        .arg(root.join("launch_notes/ecm_lcd.launch.py"))
        .output()
        .expect("python3 (standard library only) reads the launch file");
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    let argv: Vec<String> = serde_json::from_slice(&out.stdout).unwrap();
    assert_eq!(argv[..2], ["ecm-lcd", "node"], "{argv:?}");

    // The whole command line parses as the binary parses it.
    let cli = Cli::try_parse_from(&argv).unwrap_or_else(|e| panic!("{argv:?}: {e}"));
    let EcmCommand::Node(node) = cli.command else { panic!("not the node command: {argv:?}") };
    // Beside a tracker by default: its keyframes only, reliably (each one matters).
    assert_eq!(node.input, ecm_lcd::ros::node::FrameInputs::Keyframes, "{argv:?}");
    assert_eq!(node.input_qos, ecm_lcd::ros::node::InputQos::Reliable, "{argv:?}");
    assert_eq!(node.ros_args.first().map(String::as_str), Some("--ros-args"));
    let ros = RosArgs::parse(&node.ros_args, DEFAULT_NODE_NAME).unwrap();
    assert_eq!(ros.node_name(DEFAULT_NODE_NAME), DEFAULT_NODE_NAME);

    // Every input topic is remapped (the calibration and depth too: verification and metric poses
    // need them), and every remap renames one of the node's topics.
    let topics = [KEYFRAMES_TOPIC, IMAGE_TOPIC, COMPRESSED_TOPIC, CAMERA_INFO_TOPIC, DEPTH_TOPIC];
    for (from, to) in &ros.remaps {
        assert!(topics.contains(&from.as_str()), "remap of {from}, which the node does not have");
        assert!(to.starts_with('/'), "{from} -> {to}");
    }
    for topic in topics {
        assert!(ros.remaps.iter().any(|(from, _)| from == topic), "{topic} is not remapped: {:?}", ros.remaps);
    }

    // The default params file is the shipped one, relative to the repository, and it is the defaults.
    assert_eq!(ros.params_files.len(), 1);
    let params = Params::load(&root.join(&ros.params_files[0]), DEFAULT_NODE_NAME).unwrap();
    assert!(params == Params::default(), "{} differs from the built-in defaults", ros.params_files[0].display());
}
