//! Private network namespaces for programs that start DDS participants on a shared machine (tests and
//! the latency benchmark): a fresh namespace with only loopback up and multicast routed to it, so DDS
//! discovery reaches the processes started inside and nothing else.
//!
//! How a process knows it is inside: [`private_netns_command`] runs the program through a shell inside
//! the new namespace that exports [`MARKER_VAR`] = that namespace's id (`readlink /proc/self/ns/net`);
//! [`inside_private_netns`] compares the variable with the current namespace, so a marker inherited
//! into some other namespace (e.g. a shell started outside) does not count.

use std::path::Path;
use std::process::Command;

/// Environment variable holding the id of the private namespace a program was started in.
pub const MARKER_VAR: &str = "ECM_LCD_PRIVATE_NETNS";

/// The current network namespace, as `net:[inode]`.
pub fn current_netns() -> Option<String> {
    std::fs::read_link("/proc/self/ns/net").ok().map(|p| p.to_string_lossy().into_owned())
}

/// True when this process runs in the private namespace that [`private_netns_command`] made.
pub fn inside_private_netns() -> bool {
    match (std::env::var(MARKER_VAR), current_netns()) {
        (Ok(marker), Some(current)) => marker == current,
        _ => false,
    }
}

fn is_root() -> bool {
    Command::new("id").arg("-u").output().map(|o| o.stdout.starts_with(b"0\n")).unwrap_or(false)
}

/// A command that runs `program` in a new network namespace (util-linux `unshare -n`, or `-rn` with a
/// user namespace when not root), with loopback up and multicast routed over it. Add the program's
/// arguments with `.args(...)`.
pub fn private_netns_command(program: &Path) -> Command {
    let mut command = Command::new("unshare");
    command
        .arg(if is_root() { "-n" } else { "-rn" })
        .args(["sh", "-c"])
        .arg(format!(
            "ip link set lo up || {{ echo 'cannot bring up loopback in the private network namespace' >&2; exit 1; }}; \
             ip route add 224.0.0.0/4 dev lo 2>/dev/null || true; \
             {MARKER_VAR}=$(readlink /proc/self/ns/net) && export {MARKER_VAR} && exec \"$0\" \"$@\""
        ))
        .arg(program);
    command
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_marker_from_another_namespace_does_not_count() {
        // This process was not started by private_netns_command: whatever the environment says, the
        // marker must name the current namespace to count.
        if let Some(current) = current_netns() {
            let marker = std::env::var(MARKER_VAR).ok();
            assert_eq!(inside_private_netns(), marker.as_deref() == Some(current.as_str()));
            assert!(current.starts_with("net:["), "{current}");
        }
    }

    #[test]
    fn the_command_enters_a_new_namespace_and_sets_the_marker() {
        // `sh -c` prints the marker and the namespace it runs in; no DDS participant is started.
        let out = private_netns_command(Path::new("sh"))
            .args(["-c", &format!("echo ${MARKER_VAR}; readlink /proc/self/ns/net; cat /proc/self/net/dev")])
            .output()
            .expect("running unshare");
        let text = String::from_utf8_lossy(&out.stdout);
        assert!(out.status.success(), "{text}{}", String::from_utf8_lossy(&out.stderr));
        let lines: Vec<&str> = text.lines().collect();
        assert_eq!(lines[0], lines[1], "marker equals the inner namespace");
        assert_ne!(Some(lines[1].to_string()), current_netns(), "a different namespace from ours");
        // Only loopback in there (the two header lines of /proc/net/dev, then one interface).
        let interfaces: Vec<&str> = lines[4..].iter().map(|l| l.trim().split(':').next().unwrap_or("")).collect();
        assert_eq!(interfaces, vec!["lo"], "{text}");
    }
}
