//! The CPU limit a process runs under: its cgroup's CFS quota over the
//! quota's period (what a container's `limits: cpu` sets), the least of the
//! process's cgroup and its ancestors, read from cgroup v2's `cpu.max` or
//! cgroup v1's `cpu.cfs_quota_us` and `cpu.cfs_period_us`.

use std::path::{Path, PathBuf};

/// Where the cgroup file systems are mounted.
const CGROUP_ROOT: &str = "/sys/fs/cgroup";

/// The CPU limit of this process in cores, or `None` when it has none (or
/// it cannot be read: not Linux, no cgroup file system).
pub fn cgroup_cpu_limit() -> Option<f64> {
    let membership = std::fs::read_to_string("/proc/self/cgroup").ok()?;
    limit_in(Path::new(CGROUP_ROOT), &membership)
}

/// The least limit of the cgroups listed in `membership` (the text of
/// `/proc/self/cgroup`) and their ancestors, under `root`.
fn limit_in(root: &Path, membership: &str) -> Option<f64> {
    let read = |path: PathBuf| std::fs::read_to_string(path).ok();
    let mut least: Option<f64> = None;
    let mut consider = |limit: Option<f64>| {
        if let Some(cores) = limit {
            least = Some(least.map_or(cores, |l| l.min(cores)));
        }
    };
    for line in membership.lines() {
        let mut fields = line.splitn(3, ':');
        let (Some(_), Some(controllers), Some(path)) = (fields.next(), fields.next(), fields.next()) else {
            continue;
        };
        if controllers.is_empty() {
            // cgroup v2: one hierarchy, `cpu.max` in each group.
            for dir in ancestors(root, path) {
                consider(read(dir.join("cpu.max")).as_deref().and_then(parse_cpu_max));
            }
        } else if controllers.split(',').any(|c| c == "cpu") {
            // cgroup v1: the cpu controller's own hierarchy, mounted as
            // `cpu` or `cpu,cpuacct`.
            for mount in ["cpu", "cpu,cpuacct", "cpuacct,cpu"] {
                for dir in ancestors(&root.join(mount), path) {
                    let quota = read(dir.join("cpu.cfs_quota_us"));
                    let period = read(dir.join("cpu.cfs_period_us"));
                    consider(quota.zip(period).and_then(|(q, p)| parse_cfs(&q, &p)));
                }
            }
        }
    }
    least
}

/// `mount` joined with each prefix of the cgroup `path`, the group itself
/// first, the mount's root last. Paths that climb (`..`) are not followed.
fn ancestors(mount: &Path, path: &str) -> Vec<PathBuf> {
    let parts: Vec<&str> = path.split('/').filter(|p| !p.is_empty()).collect();
    if parts.iter().any(|p| *p == "." || *p == "..") {
        return vec![mount.to_path_buf()];
    }
    (0..=parts.len()).rev().map(|n| parts[..n].iter().fold(mount.to_path_buf(), |dir, part| dir.join(part))).collect()
}

/// cgroup v2's `cpu.max`: `$MAX $PERIOD`, `max` for no limit.
fn parse_cpu_max(text: &str) -> Option<f64> {
    let mut fields = text.split_whitespace();
    let quota = fields.next()?;
    let period = fields.next().unwrap_or("100000");
    if quota == "max" {
        return None;
    }
    cores(quota.parse().ok()?, period.parse().ok()?)
}

/// cgroup v1's quota and period, in microseconds; a quota of -1 for none.
fn parse_cfs(quota: &str, period: &str) -> Option<f64> {
    let quota: i64 = quota.trim().parse().ok()?;
    let period: i64 = period.trim().parse().ok()?;
    cores(u64::try_from(quota).ok()?, u64::try_from(period).ok()?)
}

/// A quota over a period, in cores; `None` unless both are positive.
fn cores(quota_us: u64, period_us: u64) -> Option<f64> {
    (quota_us > 0 && period_us > 0).then(|| quota_us as f64 / period_us as f64)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn quotas_read_as_cores() {
        assert_eq!(parse_cpu_max("25000 100000\n"), Some(0.25));
        assert_eq!(parse_cpu_max("200000 100000"), Some(2.0));
        assert_eq!(parse_cpu_max("max 100000\n"), None);
        assert_eq!(parse_cpu_max("0 100000"), None);
        assert_eq!(parse_cpu_max("garbage"), None);
        assert_eq!(parse_cpu_max(""), None);
        assert_eq!(parse_cfs("50000\n", "100000\n"), Some(0.5));
        assert_eq!(parse_cfs("-1", "100000"), None);
        assert_eq!(parse_cfs("50000", "0"), None);
        assert_eq!(parse_cfs("x", "100000"), None);
    }

    /// Writes `files` (path under the root, content) into a fresh directory.
    fn cgroup_tree(files: &[(&str, &str)]) -> tempfile::TempDir {
        let root = tempfile::tempdir().unwrap();
        for (path, content) in files {
            let file = root.path().join(path);
            std::fs::create_dir_all(file.parent().unwrap()).unwrap();
            std::fs::write(file, content).unwrap();
        }
        root
    }

    #[test]
    fn a_v2_group_is_limited_by_the_least_of_itself_and_its_ancestors() {
        let root = cgroup_tree(&[
            ("cpu.max", "max 100000\n"),
            ("kubepods/cpu.max", "150000 100000\n"),
            ("kubepods/pod1/cpu.max", "max 100000\n"),
            ("kubepods/pod1/app/cpu.max", "50000 100000\n"),
        ]);
        assert_eq!(limit_in(root.path(), "0::/kubepods/pod1/app\n"), Some(0.5));
        assert_eq!(limit_in(root.path(), "0::/kubepods/pod1\n"), Some(1.5));
        assert_eq!(limit_in(root.path(), "0::/\n"), None);
        // A namespaced container sees its own group as the root.
        let own = cgroup_tree(&[("cpu.max", "25000 100000\n")]);
        assert_eq!(limit_in(own.path(), "0::/\n"), Some(0.25));
    }

    #[test]
    fn a_v1_group_is_read_from_the_cpu_hierarchy() {
        let root = cgroup_tree(&[
            ("cpu,cpuacct/cpu.cfs_quota_us", "-1\n"),
            ("cpu,cpuacct/cpu.cfs_period_us", "100000\n"),
            ("cpu,cpuacct/docker/abc/cpu.cfs_quota_us", "25000\n"),
            ("cpu,cpuacct/docker/abc/cpu.cfs_period_us", "100000\n"),
            ("memory/docker/abc/cpu.cfs_quota_us", "1000\n"),
            ("memory/docker/abc/cpu.cfs_period_us", "100000\n"),
        ]);
        let membership = "12:memory:/docker/abc\n4:cpu,cpuacct:/docker/abc\n1:name=systemd:/docker/abc\n0::/\n";
        assert_eq!(limit_in(root.path(), membership), Some(0.25));
        assert_eq!(limit_in(root.path(), "4:cpu,cpuacct:/\n"), None);
    }

    #[test]
    fn paths_that_climb_are_not_followed() {
        let tree = cgroup_tree(&[("cgroup/cpu.max", "max 100000\n"), ("cpu.max", "1000 100000\n")]);
        let root = tree.path().join("cgroup");
        assert_eq!(limit_in(&root, "0::/../\n"), None);
        assert_eq!(limit_in(&root, "0::/a/../..\n"), None);
    }

    #[test]
    fn no_membership_no_limit() {
        let root = cgroup_tree(&[]);
        assert_eq!(limit_in(root.path(), ""), None);
        assert_eq!(limit_in(root.path(), "not a cgroup line\n"), None);
    }
}
