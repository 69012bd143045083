//! The six standard parameter services (`get_parameters`, `get_parameter_types`, `set_parameters`,
//! `set_parameters_atomically`, `list_parameters`, `describe_parameters`) served by the node itself
//! instead of ros2-client's spinner, because ros2-client 0.12 describes every parameter as
//! "(description missing, not implemented)" without ranges. Here `describe_parameters` answers from
//! [`crate::config::param_specs`]: description, integer/floating-point range, allowed strings (as
//! `additional_constraints`) and `read_only`. Values live in ros2-client's node store, so `set` runs the
//! node's validator and set action and publishes `/parameter_events` exactly as before.

use anyhow::Result;
use log::{debug, warn};
use ros2_client::{
    dds::rustdds::mio1::{Interest, Registry, Token},
    parameters::raw,
    rcl_interfaces::{
        DescribeParametersRequest, DescribeParametersResponse, GetParameterTypesRequest, GetParameterTypesResponse,
        GetParametersRequest, GetParametersResponse, ListParametersRequest, ListParametersResponse,
        ListParametersResult, SetParametersAtomicallyResponse, SetParametersRequest, SetParametersResponse,
    },
    Context, Node, Parameter, ParameterValue,
};

use super::params::{to_ros, validate_change, USE_SIM_TIME};
use super::service::FramedServer;
use crate::config::{param_spec, ParamRange, Params};

/// The servers ([`FramedServer`]: both RMW request framings); [`ParamServices::serve`] answers
/// whatever requests are waiting.
pub struct ParamServices {
    get: FramedServer<GetParametersRequest, GetParametersResponse>,
    get_types: FramedServer<GetParameterTypesRequest, GetParameterTypesResponse>,
    set: FramedServer<SetParametersRequest, SetParametersResponse>,
    // rcl_interfaces/SetParametersAtomically's request has the same layout as SetParameters'.
    set_atomically: FramedServer<SetParametersRequest, SetParametersAtomicallyResponse>,
    list: FramedServer<ListParametersRequest, ListParametersResponse>,
    describe: FramedServer<DescribeParametersRequest, DescribeParametersResponse>,
    fqn: String,
}

/// The descriptor of one parameter, from the table.
pub fn describe(name: &str, value: Option<&ParameterValue>) -> raw::ParameterDescriptor {
    let r#type = value.map_or(0, |v| raw::ParameterValue::from(v.clone()).ptype);
    let mut d = raw::ParameterDescriptor {
        name: name.to_string(),
        r#type,
        description: String::new(),
        additional_constraints: String::new(),
        read_only: false,
        dynamic_typing: false,
        floating_point_range: vec![],
        integer_range: vec![],
    };
    if name == USE_SIM_TIME {
        d.description = "Use the /clock topic as the node's time source (ROS built-in).".into();
    } else if let Some(spec) = param_spec(name) {
        d.description = spec.description.to_string();
        d.read_only = spec.read_only;
        match spec.range {
            ParamRange::Any => {}
            ParamRange::Integer { min, max, step } => {
                d.integer_range =
                    vec![raw::IntegerRange { from_value: min, to_value: max, step: i64::try_from(step).unwrap_or(0) }]
            }
            ParamRange::Double { min, max, step } => {
                d.floating_point_range = vec![raw::FloatingPointRange { from_value: min, to_value: max, step }]
            }
            ParamRange::OneOf(allowed) => d.additional_constraints = format!("one of: {}", allowed.join(", ")),
        }
    } else {
        d.description = "unknown parameter".into();
    }
    d
}

/// `list_parameters` with rclcpp's semantics (depth 0 = unlimited; prefixes select `prefix` and
/// `prefix.*`; the result's prefixes are the distinct namespaces of the listed names).
pub fn list(names: &[String], prefixes: &[String], depth: u64) -> ListParametersResult {
    let dots = |s: &str| s.matches('.').count() as u64;
    let listed: Vec<String> = names
        .iter()
        .filter(|name| {
            if prefixes.is_empty() {
                depth == 0 || dots(name) < depth
            } else {
                prefixes.iter().any(|p| {
                    name.as_str() == p
                        || name
                            .strip_prefix(p.as_str())
                            .and_then(|r| r.strip_prefix('.'))
                            .is_some_and(|rest| depth == 0 || dots(rest) < depth)
                })
            }
        })
        .cloned()
        .collect();
    let mut namespaces: Vec<String> =
        listed.iter().filter_map(|n| n.rsplit_once('.').map(|(ns, _)| ns.to_string())).collect();
    namespaces.sort();
    namespaces.dedup();
    ListParametersResult { names: listed, prefixes: namespaces }
}

impl ParamServices {
    pub fn create(context: &Context, fqn: &str) -> Result<Self> {
        let name = |service: &str| format!("{fqn}/{service}");
        const PACKAGE: &str = "rcl_interfaces";
        Ok(ParamServices {
            get: FramedServer::new(context, &name("get_parameters"), PACKAGE, "GetParameters")?,
            get_types: FramedServer::new(context, &name("get_parameter_types"), PACKAGE, "GetParameterTypes")?,
            set: FramedServer::new(context, &name("set_parameters"), PACKAGE, "SetParameters")?,
            set_atomically: FramedServer::new(
                context,
                &name("set_parameters_atomically"),
                PACKAGE,
                "SetParametersAtomically",
            )?,
            list: FramedServer::new(context, &name("list_parameters"), PACKAGE, "ListParameters")?,
            describe: FramedServer::new(context, &name("describe_parameters"), PACKAGE, "DescribeParameters")?,
            fqn: fqn.to_string(),
        })
    }

    /// Registers every server for readiness events, with tokens `first`, `first + 1`, ...
    pub fn register(&mut self, registry: &Registry, first: usize) -> std::io::Result<()> {
        registry.register(&mut self.get, Token(first), Interest::READABLE)?;
        registry.register(&mut self.get_types, Token(first + 1), Interest::READABLE)?;
        registry.register(&mut self.set, Token(first + 2), Interest::READABLE)?;
        registry.register(&mut self.set_atomically, Token(first + 3), Interest::READABLE)?;
        registry.register(&mut self.list, Token(first + 4), Interest::READABLE)?;
        registry.register(&mut self.describe, Token(first + 5), Interest::READABLE)
    }

    /// Answers every waiting request. `live` holds the current values for atomic validation.
    pub fn serve(&self, node: &Node, live: &std::sync::Mutex<Params>) {
        while let Some((id, req)) = self.get.receive() {
            let values = req
                .names
                .iter()
                .map(|n| raw::ParameterValue::from(node.get_parameter(n).unwrap_or(ParameterValue::NotSet)))
                .collect();
            self.reply(self.get.reply(&id, &GetParametersResponse { values }), "get_parameters");
        }
        while let Some((id, req)) = self.get_types.receive() {
            let values = req
                .names
                .iter()
                .map(|n| raw::ParameterValue::from(node.get_parameter(n).unwrap_or(ParameterValue::NotSet)).ptype)
                .collect();
            self.reply(self.get_types.reply(&id, &GetParameterTypesResponse { values }), "get_parameter_types");
        }
        while let Some((id, req)) = self.set.receive() {
            let results = req
                .parameter
                .into_iter()
                .map(Parameter::from)
                .map(|Parameter { name, value }| node.set_parameter(&name, converted(live, &name, value)).into())
                .collect();
            self.reply(self.set.reply(&id, &SetParametersResponse { results }), "set_parameters");
        }
        while let Some((id, req)) = self.set_atomically.receive() {
            let params: Vec<Parameter> = req.parameter.into_iter().map(Parameter::from).collect();
            // All or nothing: check every change against one trial copy first.
            let mut trial = live.lock().unwrap_or_else(|e| e.into_inner()).clone();
            let mut checked = Vec::new();
            let check = params.iter().try_for_each(|p| {
                if p.name == USE_SIM_TIME {
                    checked.push((p.name.clone(), p.value.clone()));
                    return matches!(p.value, ParameterValue::Boolean(_))
                        .then_some(())
                        .ok_or_else(|| "use_sim_time must be a bool".to_string());
                }
                let value = validate_change(&trial, &p.name, &p.value).map_err(|e| e.to_string())?;
                // The node's store refuses a change of type after the changes before it were
                // applied: what the conversions leave of another type is refused here, so nothing is.
                if changes_type(node.get_parameter(&p.name).as_ref(), &to_ros(&value)) {
                    return Err(format!("{}: cannot change the parameter's type", p.name));
                }
                checked.push((p.name.clone(), to_ros(&value)));
                trial.set(&p.name, value).map_err(|e| format!("{}: {e}", p.name))
            });
            let result =
                check.and_then(|()| checked.into_iter().try_for_each(|(name, value)| node.set_parameter(&name, value)));
            self.reply(
                self.set_atomically.reply(&id, &SetParametersAtomicallyResponse { result: result.into() }),
                "set_parameters_atomically",
            );
        }
        while let Some((id, req)) = self.list.receive() {
            let result = list(&node.list_parameters(), &req.prefixes, req.depth);
            self.reply(self.list.reply(&id, &ListParametersResponse { result }), "list_parameters");
        }
        while let Some((id, req)) = self.describe.receive() {
            let values = req.names.iter().map(|n| describe(n, node.get_parameter(n).as_ref())).collect();
            self.reply(self.describe.reply(&id, &DescribeParametersResponse { values }), "describe_parameters");
        }
    }

    fn reply(&self, result: Result<()>, service: &str) {
        match result {
            Ok(()) => debug!("[{}] answered {service}", self.fqn),
            Err(e) => warn!("[{}] {service} response failed: {e:#}", self.fqn),
        }
    }
}

/// Whether setting `new` on a parameter holding `existing` changes its type, which ros2-client's
/// parameter store refuses (an unset value on either side is no type).
/// `value` for the parameter `name` in the node's own type, where the node's conversions apply (an
/// integer for a double, `yes` for a bool, a bool for `on`/`off`: `crate::config`): the node's store
/// refuses a change of type before the validator sees it. Other values go as they came, for the
/// validator to refuse with its reason.
fn converted(live: &std::sync::Mutex<Params>, name: &str, value: ParameterValue) -> ParameterValue {
    let current = live.lock().unwrap_or_else(|e| e.into_inner()).clone();
    match validate_change(&current, name, &value) {
        Ok(converted) if name != USE_SIM_TIME => to_ros(&converted),
        _ => value,
    }
}

fn changes_type(existing: Option<&ParameterValue>, new: &ParameterValue) -> bool {
    match existing {
        Some(existing) if !matches!(existing, ParameterValue::NotSet) && !matches!(new, ParameterValue::NotSet) => {
            std::mem::discriminant(existing) != std::mem::discriminant(new)
        }
        _ => false,
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::config::param_specs;

    #[test]
    fn a_change_of_type_is_told_before_anything_is_applied() {
        let double = ParameterValue::Double(0.9);
        assert!(changes_type(Some(&double), &ParameterValue::Integer(1)));
        assert!(!changes_type(Some(&double), &ParameterValue::Double(1.0)));
        assert!(!changes_type(None, &ParameterValue::Integer(1)));
        assert!(!changes_type(Some(&ParameterValue::NotSet), &ParameterValue::Integer(1)));
    }

    #[test]
    fn descriptors_carry_the_table() {
        for spec in param_specs() {
            let d = describe(spec.name, Some(&super::super::params::to_ros(&spec.default)));
            assert_eq!(d.description, spec.description);
            assert_eq!(d.read_only, spec.read_only);
            match spec.range {
                ParamRange::Integer { min, max, .. } => {
                    assert_eq!((d.integer_range[0].from_value, d.integer_range[0].to_value), (min, max))
                }
                ParamRange::Double { min, max, .. } => {
                    assert_eq!((d.floating_point_range[0].from_value, d.floating_point_range[0].to_value), (min, max))
                }
                ParamRange::OneOf(allowed) => assert!(d.additional_constraints.contains(allowed[0])),
                ParamRange::Any => {}
            }
            assert_ne!(d.r#type, 0);
        }
        assert_eq!(describe("nope", None).r#type, 0);
    }

    #[test]
    fn listing_follows_rclcpp() {
        let names: Vec<String> = ["a", "d.x", "d.y", "d.e.z"].iter().map(|s| s.to_string()).collect();
        assert_eq!(list(&names, &[], 0).names, names);
        assert_eq!(list(&names, &[], 1).names, vec!["a"]);
        let r = list(&names, &["d".to_string()], 1);
        assert_eq!(r.names, vec!["d.x", "d.y"]);
        assert_eq!(r.prefixes, vec!["d"]);
        assert_eq!(list(&names, &["d".to_string()], 0).prefixes, vec!["d", "d.e"]);
    }
}
