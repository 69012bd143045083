//! ROS 2 parameters of the node, declared from [`crate::config::param_specs`]: initial values from
//! `--params-file` and `-p`, conversion to and from ros2-client's values, and the validator the parameter
//! services call before a change is accepted.
//!
//! Several `--params-file`s: each is loaded with [`Params::load`] (one with no section for this node is
//! passed over with a warning, as ROS 2 does); a file's values that differ from the
//! defaults override the earlier files' (so a later file cannot set a value back to its default over an
//! earlier file - a limitation of loading whole files; use `-p` for that). `-p` values come last and win.

use anyhow::{anyhow, Context, Result};
use ros2_client::ParameterValue;

use super::args::RosArgs;
use crate::config::{param_spec, param_specs, NoSectionApplies, ParamError, ParamValue, Params};

pub use crate::config::USE_SIM_TIME;

/// The parameter values the node starts with (see the module doc for precedence).
/// Returns the params and the `use_sim_time` value given in a params file or with `-p`, if any.
pub fn initial_params(args: &RosArgs, fully_qualified_node_name: &str) -> Result<(Params, Option<bool>)> {
    let mut params = Params::default();
    let defaults = Params::default();
    let mut use_sim_time = None;
    for path in &args.params_files {
        let loaded = match Params::load(path, fully_qualified_node_name) {
            Err(e) if e.downcast_ref::<NoSectionApplies>().is_some() => {
                log::warn!("{e:#}; the file is passed over");
                continue;
            }
            loaded => loaded?,
        };
        use_sim_time = loaded.use_sim_time().or(use_sim_time);
        for spec in param_specs() {
            let value = loaded.get(spec.name);
            if value != defaults.get(spec.name) {
                if let Some(value) = value {
                    params.set(spec.name, value).map_err(|reason| anyhow!("{reason} (from {})", path.display()))?;
                }
            }
        }
    }
    for (name, value) in &args.params {
        if name == USE_SIM_TIME {
            match value {
                ParamValue::Bool(b) => use_sim_time = Some(*b),
                other => return Err(anyhow!("-p use_sim_time:={other:?}: must be true or false")),
            }
            continue;
        }
        params.set(name, value.clone()).map_err(|reason| anyhow!("-p {name}:=...: {reason}"))?;
    }
    Ok((params, use_sim_time))
}

pub fn to_ros(value: &ParamValue) -> ParameterValue {
    match value {
        ParamValue::Bool(b) => ParameterValue::Boolean(*b),
        ParamValue::Integer(i) => ParameterValue::Integer(*i),
        ParamValue::Double(d) => ParameterValue::Double(*d),
        ParamValue::String(s) => ParameterValue::String(s.clone()),
    }
}

pub fn from_ros(value: &ParameterValue) -> Result<ParamValue, ParamError> {
    Ok(match value {
        ParameterValue::Boolean(b) => ParamValue::Bool(*b),
        ParameterValue::Integer(i) => ParamValue::Integer(*i),
        ParameterValue::Double(d) => ParamValue::Double(*d),
        ParameterValue::String(s) => ParamValue::String(s.clone()),
        other => return Err(ParamError::UnsupportedType(format!("{other:?}"))),
    })
}

/// `(name, value)` for every declared parameter, in table order.
pub fn declarations(params: &Params) -> Result<Vec<(&'static str, ParameterValue)>> {
    param_specs()
        .iter()
        .map(|spec| {
            let value = params.get(spec.name).with_context(|| format!("no value for parameter {}", spec.name))?;
            Ok((spec.name, to_ros(&value)))
        })
        .collect()
}

/// Checks a requested runtime change against the current values: a refused change leaves them as they
/// are and says why. Setting a read-only parameter to its current value is accepted (ros2-client checks
/// every initial value this way when the node starts).
pub fn validate_change(current: &Params, name: &str, value: &ParameterValue) -> Result<ParamValue, ParamError> {
    let value = from_ros(value)?;
    let spec = param_spec(name).ok_or_else(|| ParamError::Unknown(name.to_string()))?;
    let mut trial = current.clone();
    if spec.read_only {
        if current.get(name).as_ref() == Some(&value) {
            return Ok(value);
        }
        trial.set_at_runtime(name, value.clone())?;
    } else {
        trial.set(name, value.clone())?;
    }
    Ok(trial.get(name).unwrap_or(value))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn runtime_changes_are_validated() {
        let params = Params::default();
        let spec = param_specs().iter().find(|s| !s.read_only && matches!(s.default, ParamValue::Double(_))).unwrap();
        let ok = validate_change(&params, spec.name, &to_ros(&spec.default)).unwrap();
        assert_eq!(ok, spec.default);
        let err = validate_change(&params, spec.name, &ParameterValue::String("high".into())).unwrap_err().to_string();
        assert!(err.contains(spec.name), "{err}");
        assert!(validate_change(&params, "no_such_parameter", &ParameterValue::Integer(1))
            .unwrap_err()
            .to_string()
            .contains("unknown"));
        assert!(validate_change(&params, spec.name, &ParameterValue::ByteArray(vec![1]))
            .unwrap_err()
            .to_string()
            .contains("unsupported"));
        if let Some(ro) = param_specs().iter().find(|s| s.read_only) {
            assert!(validate_change(&params, ro.name, &to_ros(&ro.default)).is_ok());
        }
    }

    #[test]
    fn command_line_beats_files_and_use_sim_time_is_separate() {
        let dir = tempfile::tempdir().unwrap();
        let spec = param_specs().iter().find(|s| !s.read_only && matches!(s.default, ParamValue::Double(_))).unwrap();
        let ParamValue::Double(default) = spec.default else { unreachable!() };
        let file = dir.path().join("p.yaml");
        let from_file = ParamValue::Double(default * 0.5);
        let from_cli = ParamValue::Double(default * 0.25);
        std::fs::write(&file, format!("/**:\n  ros__parameters:\n    {}: {}\n", spec.name, default * 0.5)).unwrap();
        let mut args = RosArgs { params_files: vec![file.clone()], ..RosArgs::default() };
        let (p, sim) = initial_params(&args, "/ecm_lcd").unwrap();
        assert_eq!(p.get(spec.name), Some(from_file));
        assert_eq!(sim, None);
        args.params = vec![(spec.name.to_string(), from_cli.clone()), (USE_SIM_TIME.into(), ParamValue::Bool(true))];
        let (p, sim) = initial_params(&args, "/ecm_lcd").unwrap();
        assert_eq!(p.get(spec.name), Some(from_cli));
        assert_eq!(sim, Some(true));
        args.params = vec![("bogus".into(), ParamValue::Integer(1))];
        assert!(format!("{:#}", initial_params(&args, "/ecm_lcd").unwrap_err()).contains("bogus"));
        // A params file may give use_sim_time too (launch files for bag replays do); -p wins.
        let sim_file = dir.path().join("sim.yaml");
        std::fs::write(&sim_file, "/**:\n  ros__parameters:\n    use_sim_time: false\n").unwrap();
        let sim_on_command_line = vec![(USE_SIM_TIME.into(), ParamValue::Bool(true))];
        let both = RosArgs { params_files: vec![sim_file.clone()], params: sim_on_command_line, ..RosArgs::default() };
        assert_eq!(initial_params(&both, "/ecm_lcd").unwrap().1, Some(true));
        let from_files = RosArgs { params_files: vec![sim_file.clone()], ..RosArgs::default() };
        assert_eq!(initial_params(&from_files, "/ecm_lcd").unwrap().1, Some(false));
        std::fs::write(&sim_file, "/**:\n  ros__parameters:\n    use_sim_time: 1\n").unwrap();
        let err = format!("{:#}", initial_params(&from_files, "/ecm_lcd").unwrap_err());
        assert!(err.contains("use_sim_time") && err.contains("true or false"), "{err}");
        // A file for other nodes only is passed over (a shared file); a broken one is still an error.
        let others = dir.path().join("others.yaml");
        std::fs::write(&others, "camera:\n  ros__parameters:\n    exposure: 3\n").unwrap();
        let shared = RosArgs { params_files: vec![others.clone(), file.clone()], ..RosArgs::default() };
        assert_eq!(
            initial_params(&shared, "/ecm_lcd").unwrap().0.get(spec.name),
            Some(ParamValue::Double(default * 0.5))
        );
        std::fs::write(&others, "camera: [\n").unwrap();
        assert!(initial_params(&shared, "/ecm_lcd").is_err());
    }
}
