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
    qos::History,
    rcl_interfaces::{
        DescribeParametersRequest, DescribeParametersResponse, GetParameterTypesRequest, GetParameterTypesResponse,
        GetParametersRequest, GetParametersResponse, ListParametersRequest, ListParametersResponse,
        ListParametersResult, SetParametersAtomicallyResponse, SetParametersRequest, SetParametersResponse,
    },
    Message, Name, Node, Parameter, ParameterValue, QosProfile, Server, ServiceMapping, ServiceTypeName,
};

use super::params::{validate_change, USE_SIM_TIME};
use crate::config::{param_spec, ParamRange, Params};

/// The servers; [`ParamServices::serve`] answers whatever requests are waiting.
pub struct ParamServices {
    get: Server<GetParametersRequest, GetParametersResponse>,
    get_types: Server<GetParameterTypesRequest, GetParameterTypesResponse>,
    set: Server<SetParametersRequest, SetParametersResponse>,
    // rcl_interfaces/SetParametersAtomically's request has the same layout as SetParameters'.
    set_atomically: Server<SetParametersRequest, SetParametersAtomicallyResponse>,
    list: Server<ListParametersRequest, ListParametersResponse>,
    describe: Server<DescribeParametersRequest, DescribeParametersResponse>,
    fqn: String,
}

fn server<Req: Message + Clone + 'static, Resp: Message + Clone + 'static>(
    node: &mut Node,
    fqn: &str,
    service: &str,
    type_name: &str,
) -> Result<Server<Req, Resp>> {
    let qos = QosProfile::publisher_default().history(History::KeepLast { depth: 1 });
    let name = Name::parse(&format!("{fqn}/{service}")).map_err(|e| anyhow::anyhow!("service name: {e:?}"))?;
    node.create_server(
        ServiceMapping::Enhanced,
        &name,
        &ServiceTypeName::new("rcl_interfaces", type_name),
        qos.clone(),
        qos,
    )
    .map_err(|e| anyhow::anyhow!("creating service {fqn}/{service}: {e:?}"))
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
    pub fn create(node: &mut Node, fqn: &str) -> Result<Self> {
        Ok(ParamServices {
            get: server(node, fqn, "get_parameters", "GetParameters")?,
            get_types: server(node, fqn, "get_parameter_types", "GetParameterTypes")?,
            set: server(node, fqn, "set_parameters", "SetParameters")?,
            set_atomically: server(node, fqn, "set_parameters_atomically", "SetParametersAtomically")?,
            list: server(node, fqn, "list_parameters", "ListParameters")?,
            describe: server(node, fqn, "describe_parameters", "DescribeParameters")?,
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
        while let Ok(Some((id, req))) = self.get.receive_request() {
            let values = req
                .names
                .iter()
                .map(|n| raw::ParameterValue::from(node.get_parameter(n).unwrap_or(ParameterValue::NotSet)))
                .collect();
            self.reply(self.get.send_response(id, GetParametersResponse { values }), "get_parameters");
        }
        while let Ok(Some((id, req))) = self.get_types.receive_request() {
            let values = req
                .names
                .iter()
                .map(|n| raw::ParameterValue::from(node.get_parameter(n).unwrap_or(ParameterValue::NotSet)).ptype)
                .collect();
            self.reply(self.get_types.send_response(id, GetParameterTypesResponse { values }), "get_parameter_types");
        }
        while let Ok(Some((id, req))) = self.set.receive_request() {
            let results = req
                .parameter
                .into_iter()
                .map(Parameter::from)
                .map(|Parameter { name, value }| node.set_parameter(&name, value).into())
                .collect();
            self.reply(self.set.send_response(id, SetParametersResponse { results }), "set_parameters");
        }
        while let Ok(Some((id, req))) = self.set_atomically.receive_request() {
            let params: Vec<Parameter> = req.parameter.into_iter().map(Parameter::from).collect();
            // All or nothing: check every change against one trial copy first.
            let mut trial = live.lock().unwrap_or_else(|e| e.into_inner()).clone();
            let check = params.iter().try_for_each(|p| {
                if p.name == USE_SIM_TIME {
                    return matches!(p.value, ParameterValue::Boolean(_))
                        .then_some(())
                        .ok_or_else(|| "use_sim_time must be a bool".to_string());
                }
                let value = validate_change(&trial, &p.name, &p.value)?;
                trial.set(&p.name, value).map_err(|e| format!("{}: {e}", p.name))
            });
            let result = check.and_then(|()| params.into_iter().try_for_each(|p| node.set_parameter(&p.name, p.value)));
            self.reply(
                self.set_atomically.send_response(id, SetParametersAtomicallyResponse { result: result.into() }),
                "set_parameters_atomically",
            );
        }
        while let Ok(Some((id, req))) = self.list.receive_request() {
            let result = list(&node.list_parameters(), &req.prefixes, req.depth);
            self.reply(self.list.send_response(id, ListParametersResponse { result }), "list_parameters");
        }
        while let Ok(Some((id, req))) = self.describe.receive_request() {
            let values = req.names.iter().map(|n| describe(n, node.get_parameter(n).as_ref())).collect();
            self.reply(self.describe.send_response(id, DescribeParametersResponse { values }), "describe_parameters");
        }
    }

    fn reply<E: std::fmt::Debug>(&self, result: Result<(), E>, service: &str) {
        match result {
            Ok(()) => debug!("[{}] answered {service}", self.fqn),
            Err(e) => warn!("[{}] {service} response failed: {e:?}", self.fqn),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::config::param_specs;

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
