//! ROS 2 command-line arguments (`--ros-args ... [--]`), parsed as rcl does, so `ros2 run` / `ros2 launch`
//! can start `ecm-lcd node` like any ROS node:
//! `-r/--remap [node:]from:=to` (topic remaps and the special `__ns`, `__node`/`__name`),
//! `-p/--param [node:]name:=value` (value read as YAML: `true`, `3`, `0.4`, `text`),
//! `--params-file FILE`, `--log-level [logger:=]LEVEL`; the other rcl logging flags and `-e/--enclave`
//! are accepted and ignored (with a note in the log), anything else is an error.
//!
//! Interpretation (as rcl/rclcpp): several `--ros-args` sections may appear, each ends at `--` or at the
//! end. A rule prefixed `node:` applies only when `node` is this node's final name. Parameter values
//! come from, in rising precedence: the defaults, the params files (in order), the `-p` assignments (in
//! order) - so `-p` beats a file whatever their order on the line. Remaps compare names after expansion
//! against the node's namespace (`keyframes` and `/ns/keyframes` are the same topic for a node in `/ns`);
//! `~/x` expands to `<ns>/<node>/x`. `use_sim_time` is an ordinary `-p` parameter here (ros2-client knows
//! it). The first matching remap rule wins.

use anyhow::{bail, Context, Result};
use std::path::PathBuf;

use crate::config::ParamValue;

/// Everything the node takes from `--ros-args`.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct RosArgs {
    /// `-r __node:=NAME` (None: the default name).
    pub node_name: Option<String>,
    /// `-r __ns:=/NS` (None: `/`).
    pub namespace: Option<String>,
    /// Topic remaps `(from, to)` that apply to this node, in command-line order.
    pub remaps: Vec<(String, String)>,
    /// `-p name:=value` assignments that apply to this node, in order.
    pub params: Vec<(String, ParamValue)>,
    /// `--params-file` paths, in order.
    pub params_files: Vec<PathBuf>,
    /// `--log-level LEVEL` for this process's loggers (None: leave as configured).
    pub log_level: Option<log::LevelFilter>,
    /// Flags accepted for compatibility but without effect here, for one log line.
    pub ignored: Vec<String>,
}

/// A rule with an optional `node:` prefix, as it came from the command line.
#[derive(Clone, Debug)]
struct Targeted<T> {
    node: Option<String>,
    rule: T,
}

/// Splits `[node:]lhs:=rhs`.
fn split_rule(text: &str) -> Result<(Option<String>, String, String)> {
    let (lhs, rhs) = text.split_once(":=").with_context(|| format!("expected NAME:=VALUE, got {text:?}"))?;
    // A node prefix is `node:` before the name; `~/x` and `/x` contain no single colon.
    let (node, name) = match lhs.split_once(':') {
        Some((node, name)) if !node.is_empty() && !name.is_empty() => (Some(node.to_string()), name.to_string()),
        Some(_) => bail!("bad rule {text:?}: empty node or name around ':'"),
        None => (None, lhs.to_string()),
    };
    if name.is_empty() {
        bail!("bad rule {text:?}: empty name before ':='");
    }
    Ok((node, name, rhs.to_string()))
}

/// A `-p` value read as YAML, as rcl does (`true` is a bool, `3` an integer, `0.4` a double, other text a
/// string). Arrays and maps are refused: no ecm-lcd parameter takes one.
pub fn parse_param_value(text: &str) -> Result<ParamValue> {
    let value: serde_yaml_ng::Value =
        serde_yaml_ng::from_str(text).with_context(|| format!("parameter value {text:?} is not valid YAML"))?;
    yaml_to_param(&value).with_context(|| format!("parameter value {text:?}"))
}

/// One YAML scalar as a parameter value.
pub fn yaml_to_param(value: &serde_yaml_ng::Value) -> Result<ParamValue> {
    use serde_yaml_ng::Value;
    Ok(match value {
        Value::Bool(b) => ParamValue::Bool(*b),
        Value::Number(n) if n.is_i64() => ParamValue::Integer(n.as_i64().unwrap()),
        Value::Number(n) if n.is_f64() => ParamValue::Double(n.as_f64().unwrap()),
        Value::Number(n) => bail!("integer {n} does not fit in int64"),
        Value::String(s) => ParamValue::String(s.clone()),
        // `-p name:=` (empty) is the empty string, as `ros2 param set` would give it.
        Value::Null => ParamValue::String(String::new()),
        Value::Sequence(_) | Value::Mapping(_) | Value::Tagged(_) => {
            bail!("only scalar values (bool, integer, double, string) are supported")
        }
    })
}

/// Checks a ROS base name (node name): letters, digits, `_`, not starting with a digit.
fn check_base_name(name: &str) -> Result<()> {
    let ok = !name.is_empty()
        && name.chars().all(|c| c.is_ascii_alphanumeric() || c == '_')
        && !name.starts_with(|c: char| c.is_ascii_digit());
    if !ok {
        bail!("invalid node name {name:?}: use letters, digits and '_', not starting with a digit");
    }
    Ok(())
}

/// Normalises a namespace to `/a/b` form (`/` for the root).
fn normalise_namespace(ns: &str) -> Result<String> {
    let trimmed = ns.trim_matches('/');
    if trimmed.is_empty() {
        return Ok("/".to_string());
    }
    for token in trimmed.split('/') {
        check_base_name(token).with_context(|| format!("invalid namespace {ns:?}"))?;
    }
    Ok(format!("/{trimmed}"))
}

impl RosArgs {
    /// Parses the arguments after the program's own (the ones clap leaves), for a node whose default name
    /// is `default_node_name`. Arguments outside `--ros-args` sections are an error: the node takes none.
    pub fn parse<S: AsRef<str>>(args: &[S], default_node_name: &str) -> Result<RosArgs> {
        let mut remaps: Vec<Targeted<(String, String)>> = Vec::new();
        let mut params: Vec<Targeted<(String, ParamValue)>> = Vec::new();
        let mut out = RosArgs::default();
        let mut in_ros_args = false;
        let mut iter = args.iter().map(|a| a.as_ref());
        while let Some(arg) = iter.next() {
            if !in_ros_args {
                if arg == "--ros-args" {
                    in_ros_args = true;
                    continue;
                }
                bail!("unexpected argument {arg:?} (ROS arguments go after --ros-args)");
            }
            let mut value_of = |flag: &str| -> Result<String> {
                iter.next().map(str::to_string).with_context(|| format!("{flag} needs a value"))
            };
            match arg {
                "--" => in_ros_args = false,
                "--ros-args" => {}
                "-r" | "--remap" => {
                    let text = value_of(arg)?;
                    let (node, from, to) = split_rule(&text).with_context(|| format!("in {arg} {text}"))?;
                    remaps.push(Targeted { node, rule: (from, to) });
                }
                "-p" | "--param" => {
                    let text = value_of(arg)?;
                    let (node, name, value) = split_rule(&text).with_context(|| format!("in {arg} {text}"))?;
                    let value = parse_param_value(&value).with_context(|| format!("in {arg} {text}"))?;
                    params.push(Targeted { node, rule: (name, value) });
                }
                "--params-file" => out.params_files.push(PathBuf::from(value_of(arg)?)),
                "--log-level" => {
                    let text = value_of(arg)?;
                    // `logger:=level` sets one named logger; only the process-wide form has a meaning here.
                    let level = match text.split_once(":=") {
                        Some((_logger, level)) => {
                            out.ignored.push(format!("--log-level {text} (per-logger levels: using {level} for all)"));
                            level.to_string()
                        }
                        None => text.clone(),
                    };
                    out.log_level = Some(match level.to_ascii_lowercase().as_str() {
                        "debug" => log::LevelFilter::Debug,
                        "info" => log::LevelFilter::Info,
                        "warn" => log::LevelFilter::Warn,
                        "error" | "fatal" => log::LevelFilter::Error,
                        "unset" => log::LevelFilter::Trace,
                        other => bail!("--log-level: unknown level {other:?} (debug, info, warn, error, fatal)"),
                    });
                }
                "--log-config-file" | "-e" | "--enclave" => {
                    let value = value_of(arg)?;
                    out.ignored.push(format!("{arg} {value}"));
                }
                "--enable-rosout-logs"
                | "--disable-rosout-logs"
                | "--enable-stdout-logs"
                | "--disable-stdout-logs"
                | "--enable-external-lib-logs"
                | "--disable-external-lib-logs" => out.ignored.push(arg.to_string()),
                other => bail!("unknown ROS argument {other:?}"),
            }
        }

        // The node's name and namespace first: node-targeted rules depend on the final name.
        for Targeted { node, rule: (from, to) } in &remaps {
            match from.as_str() {
                "__node" | "__name" if node.as_deref().is_none_or(|n| n == default_node_name) => {
                    check_base_name(to)?;
                    out.node_name = Some(to.clone());
                }
                "__ns" if node.as_deref().is_none_or(|n| n == default_node_name) => {
                    out.namespace = Some(normalise_namespace(to)?);
                }
                _ => {}
            }
        }
        let name = out.node_name.clone().unwrap_or_else(|| default_node_name.to_string());
        let applies = |node: &Option<String>| node.as_deref().is_none_or(|n| n == name);
        out.remaps = remaps
            .into_iter()
            .filter(|t| applies(&t.node) && !matches!(t.rule.0.as_str(), "__node" | "__name" | "__ns"))
            .map(|t| t.rule)
            .collect();
        out.params = params.into_iter().filter(|t| applies(&t.node)).map(|t| t.rule).collect();
        Ok(out)
    }

    /// The node name in force.
    pub fn node_name<'a>(&'a self, default: &'a str) -> &'a str {
        self.node_name.as_deref().unwrap_or(default)
    }

    /// The namespace in force (`/` by default).
    pub fn namespace(&self) -> &str {
        self.namespace.as_deref().unwrap_or("/")
    }

    /// Fully qualified node name, e.g. `/robot1/ecm_lcd`.
    pub fn fully_qualified_node_name(&self, default: &str) -> String {
        join_name(self.namespace(), self.node_name(default))
    }

    /// The fully qualified topic `name` resolves to for this node after the remap rules.
    pub fn resolve_topic(&self, name: &str, default_node_name: &str) -> Result<String> {
        let expand = |n: &str| expand_name(n, self.namespace(), self.node_name(default_node_name));
        let expanded = expand(name)?;
        for (from, to) in &self.remaps {
            if expand(from)? == expanded {
                return expand(to);
            }
        }
        Ok(expanded)
    }
}

fn join_name(namespace: &str, base: &str) -> String {
    if namespace == "/" {
        format!("/{base}")
    } else {
        format!("{namespace}/{base}")
    }
}

/// Expands a topic name to its absolute form: `/x` stays, `~/x` is under the node, `x` under the namespace.
pub fn expand_name(name: &str, namespace: &str, node_name: &str) -> Result<String> {
    let absolute = if let Some(rest) = name.strip_prefix("~/") {
        join_name(&join_name(namespace, node_name), rest)
    } else if name == "~" {
        join_name(namespace, node_name)
    } else if name.starts_with('/') {
        name.to_string()
    } else {
        join_name(namespace, name)
    };
    let body = absolute.trim_start_matches('/');
    if body.is_empty() || body.split('/').any(|t| check_base_name(t).is_err()) {
        bail!("invalid topic name {name:?} (expanded: {absolute:?})");
    }
    Ok(absolute)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn parse(args: &[&str]) -> Result<RosArgs> {
        RosArgs::parse(args, "ecm_lcd")
    }

    #[test]
    fn typical_launch_line() {
        let a = parse(&[
            "--ros-args",
            "-r",
            "__node:=lcd",
            "-r",
            "__ns:=/robot1/",
            "--params-file",
            "/tmp/p.yaml",
            "-p",
            "threshold:=0.4",
            "-p",
            "use_sim_time:=true",
            "-p",
            "top_k:=3",
            "-p",
            "descriptor_mode:=l2",
            "-r",
            "keyframes:=/orb_slam3/keyframes",
            "--log-level",
            "debug",
        ])
        .unwrap();
        assert_eq!(a.node_name(""), "lcd");
        assert_eq!(a.namespace(), "/robot1");
        assert_eq!(a.fully_qualified_node_name("ecm_lcd"), "/robot1/lcd");
        assert_eq!(a.params_files, vec![PathBuf::from("/tmp/p.yaml")]);
        assert_eq!(
            a.params,
            vec![
                ("threshold".into(), ParamValue::Double(0.4)),
                ("use_sim_time".into(), ParamValue::Bool(true)),
                ("top_k".into(), ParamValue::Integer(3)),
                ("descriptor_mode".into(), ParamValue::String("l2".into())),
            ]
        );
        assert_eq!(a.log_level, Some(log::LevelFilter::Debug));
        assert_eq!(a.resolve_topic("keyframes", "ecm_lcd").unwrap(), "/orb_slam3/keyframes");
        assert_eq!(a.resolve_topic("loop_candidates", "ecm_lcd").unwrap(), "/robot1/loop_candidates");
        assert_eq!(a.resolve_topic("~/status", "ecm_lcd").unwrap(), "/robot1/lcd/status");
    }

    #[test]
    fn remaps_match_after_expansion_and_first_rule_wins() {
        let a = parse(&["--ros-args", "-r", "__ns:=/r", "-r", "/r/image:=/cam/rgb", "-r", "image:=/other"]).unwrap();
        assert_eq!(a.resolve_topic("image", "ecm_lcd").unwrap(), "/cam/rgb");
        assert_eq!(a.resolve_topic("/image", "ecm_lcd").unwrap(), "/image");
        let rel = parse(&["--ros-args", "-r", "__ns:=/r", "-r", "image:=camera/image_raw"]).unwrap();
        assert_eq!(rel.resolve_topic("image", "x").unwrap(), "/r/camera/image_raw");
    }

    #[test]
    fn node_targeted_rules_follow_the_final_name() {
        let a = parse(&[
            "--ros-args",
            "-r",
            "__node:=lcd",
            "-p",
            "lcd:threshold:=0.5",
            "-p",
            "other:threshold:=0.9",
            "-r",
            "other:image:=/x",
            "-r",
            "lcd:image:=/y",
        ])
        .unwrap();
        assert_eq!(a.params, vec![("threshold".into(), ParamValue::Double(0.5))]);
        assert_eq!(a.remaps, vec![("image".into(), "/y".into())]);
    }

    #[test]
    fn sections_and_separators() {
        let a = parse(&["--ros-args", "-p", "a:=1", "--", "--ros-args", "-p", "b:=x y"]).unwrap();
        assert_eq!(
            a.params,
            vec![("a".into(), ParamValue::Integer(1)), ("b".into(), ParamValue::String("x y".into()))]
        );
        assert!(parse(&[]).unwrap() == RosArgs::default());
        let ignored = parse(&["--ros-args", "--disable-rosout-logs", "-e", "/enclave"]).unwrap();
        assert_eq!(ignored.ignored.len(), 2);
    }

    #[test]
    fn bad_arguments_are_errors_with_reasons() {
        let err = |args: &[&str]| format!("{:#}", parse(args).unwrap_err());
        assert!(err(&["threshold:=1"]).contains("--ros-args"));
        assert!(err(&["--ros-args", "-p"]).contains("-p needs a value"));
        assert!(err(&["--ros-args", "-p", "threshold"]).contains("NAME:=VALUE"));
        assert!(err(&["--ros-args", "-p", "a:=[1, 2]"]).contains("scalar"));
        assert!(err(&["--ros-args", "-p", "a:={b"]).contains("YAML"));
        assert!(err(&["--ros-args", "-r", "__node:=9lives"]).contains("invalid node name"));
        assert!(err(&["--ros-args", "-r", "__ns:=/a b"]).contains("invalid namespace"));
        assert!(err(&["--ros-args", "--bogus"]).contains("unknown ROS argument"));
        assert!(err(&["--ros-args", "--log-level", "loud"]).contains("unknown level"));
        let a = parse(&["--ros-args", "-r", "image:=/bad name"]).unwrap();
        assert!(format!("{:#}", a.resolve_topic("image", "n").unwrap_err()).contains("invalid topic name"));
    }

    #[test]
    fn yaml_values() {
        assert_eq!(parse_param_value("false").unwrap(), ParamValue::Bool(false));
        assert_eq!(parse_param_value("-7").unwrap(), ParamValue::Integer(-7));
        assert_eq!(parse_param_value("1e-3").unwrap(), ParamValue::Double(1e-3));
        assert_eq!(parse_param_value("'3'").unwrap(), ParamValue::String("3".into()));
        assert_eq!(parse_param_value("").unwrap(), ParamValue::String(String::new()));
    }
}
