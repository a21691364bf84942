//! The command line: commands, their arguments and how they are read.

use std::path::PathBuf;

use clap::{Parser, Subcommand};

use exploration_proto::v1 as pb;

/// The heading under which every command's help lists how to reach the
/// executive, apart from the command's own options.
const CONNECTION: &str = "Connecting to the executive";

#[derive(Debug, Parser)]
#[command(name = "coordctl", version, about = "Watch and steer robot fleets exploring through the executive")]
pub(crate) struct Cli {
    /// The executive's address; replicas sharing a database: their addresses, comma-separated.
    #[arg(long, global = true, env = "COORDINATOR_URL", default_value = "http://127.0.0.1:50051", help_heading = CONNECTION)]
    pub(crate) server: String,
    /// The operator token (see `coordinator --operator-token`).
    #[arg(long, global = true, env = "COORDINATOR_TOKEN", hide_env_values = true, help_heading = CONNECTION)]
    pub(crate) token: Option<String>,
    /// Your name, recorded with every change you make on an executive that
    /// runs open; one that checks tokens records the name of your token.
    #[arg(long = "as", global = true, env = "USER", default_value = "operator", help_heading = CONNECTION)]
    pub(crate) actor: String,
    /// PEM CA certificate(s) to trust for an `https://` executive (default:
    /// the system's roots).
    #[arg(long, global = true, env = "COORDINATOR_TLS_CA", help_heading = CONNECTION)]
    pub(crate) tls_ca: Option<std::path::PathBuf>,
    /// PEM client certificate, when the executive asks for one (mutual TLS).
    #[arg(long, global = true, env = "COORDINATOR_TLS_CLIENT_CERT", requires = "tls_key", help_heading = CONNECTION)]
    pub(crate) tls_cert: Option<std::path::PathBuf>,
    /// PEM key of --tls-cert.
    #[arg(long, global = true, env = "COORDINATOR_TLS_CLIENT_KEY", requires = "tls_cert", help_heading = CONNECTION)]
    pub(crate) tls_key: Option<std::path::PathBuf>,
    /// Print JSON instead of tables.
    #[arg(long, global = true)]
    pub(crate) json: bool,
    #[command(subcommand)]
    pub(crate) command: Command,
}

#[derive(Debug, Subcommand)]
pub(crate) enum Command {
    /// List, show, create, pause or resume missions, or change a mission's
    /// policy (`missions` alone lists them).
    #[command(visible_alias = "mission")]
    Missions {
        #[command(subcommand)]
        command: Option<MissionCommand>,
    },
    /// List the policies the executive offers, with their parameters.
    Policies,
    /// List a mission's robots: state, task, pose, liveness.
    Robots { mission: u64 },
    /// A mission's or a robot's task timeline, newest first.
    #[command(visible_alias = "history")]
    Tasks {
        mission: u64,
        /// Only this robot's (id, or name).
        #[arg(long)]
        robot: Option<String>,
        /// Only tasks of this kind.
        #[arg(long, value_parser = ["explore", "goto", "hold", "home", "pin"])]
        kind: Option<String>,
        /// Only tasks that have not ended.
        #[arg(long)]
        open: bool,
        /// At most this many.
        #[arg(long, default_value_t = 50)]
        limit: u32,
        /// Every transition of every task, with who and why.
        #[arg(long)]
        history: bool,
    },
    /// The mission's events: policy changes, overrides, pauses, lost robots ...
    Events { mission: u64 },
    /// Give a robot an operator task, or hand it back to the policy.
    Override {
        mission: u64,
        /// The robot's name or id.
        robot: String,
        #[command(subcommand)]
        action: OverrideAction,
        /// Why, for the record.
        #[arg(long, global = true, default_value = "")]
        reason: String,
    },
    /// Pin the frontier at x,y to a robot: it explores it, the others keep
    /// away (the same as `override MISSION ROBOT pin X,Y`).
    Pin {
        mission: u64,
        robot: String,
        #[arg(value_parser = parse_point, allow_hyphen_values = true)]
        point: pb::Point,
        #[arg(long, default_value = "")]
        reason: String,
    },
    /// Forbid a rectangle (metres: x0,y0,x1,y1): no target is assigned inside.
    Forbid {
        mission: u64,
        #[arg(value_parser = parse_rect, allow_hyphen_values = true)]
        area: pb::Rect,
        #[arg(long, default_value = "")]
        reason: String,
    },
    /// Lift a forbidden region.
    Allow {
        mission: u64,
        region: u64,
        #[arg(long, default_value = "")]
        reason: String,
    },
    /// Follow a mission live: one line (or JSON object) per change.
    Watch {
        mission: u64,
        /// Stop after this many views.
        #[arg(long)]
        count: Option<usize>,
    },
    /// Give a mission its rooms and corridors (Wurm et al. 2008, §VI): the
    /// segmentation of the finished building's map at MAP (map_server YAML
    /// of the same area as the mission's map), which the `segmentation`
    /// policy then plans on; or `--online` to go back to segmenting the
    /// explored map as it grows.
    Rooms {
        mission: u64,
        #[arg(required_unless_present = "online", conflicts_with = "online")]
        map: Option<PathBuf>,
        #[arg(long)]
        online: bool,
        #[arg(long, default_value = "")]
        reason: String,
    },
    /// The fused map.
    #[command(subcommand)]
    Map(MapCommand),
    /// A consistent copy of the executive's whole database, taken while
    /// missions run, written to FILE (which must not exist); start a
    /// coordinator with `--db FILE` to resume from it.
    Backup { file: std::path::PathBuf },
}

#[derive(Debug, Subcommand)]
pub(crate) enum MapCommand {
    /// Export the fused map as a PNG: occupancy, frontier, segments, robots,
    /// targets and forbidden regions.
    Export {
        mission: u64,
        #[arg(long)]
        png: PathBuf,
        /// Size of the longer side, pixels (from 1 to 16 per cell, and at most 100 megapixels in all).
        #[arg(long, default_value_t = 1200)]
        px: u32,
        /// Tint the segmentation's segments.
        #[arg(long)]
        segments: bool,
    },
}

#[derive(Debug, Subcommand)]
pub(crate) enum MissionCommand {
    /// Every mission with its state and counters.
    List,
    /// Everything about one mission.
    Show { mission: u64 },
    /// Create a mission over the frame of a map_server YAML, or an explicit frame.
    Create {
        /// A name for people; printable text.
        #[arg(long, default_value = "mission")]
        name: String,
        /// Take the frame (size, resolution, origin) from this map.
        #[arg(long, conflicts_with_all = ["width", "height"])]
        map: Option<PathBuf>,
        /// The grid's width in cells, without --map.
        #[arg(long, requires = "height")]
        width: Option<u32>,
        /// The grid's height in cells, without --map.
        #[arg(long, requires = "width")]
        height: Option<u32>,
        /// Metres per cell (with --map: defaults to the map's).
        #[arg(long, allow_hyphen_values = true)]
        resolution: Option<f64>,
        /// World position of cell (0, 0)'s lower-left corner, x,y.
        #[arg(long, value_parser = parse_point, allow_hyphen_values = true)]
        origin: Option<pb::Point>,
        /// The coordination policy (`coordctl policies` lists them).
        #[arg(long, default_value = "burgard")]
        policy: String,
        /// A policy parameter, name=value; repeat for more.
        #[arg(long = "param", value_parser = parse_param)]
        params: Vec<(String, f64)>,
        /// Seconds without news after which a robot loses its task.
        #[arg(long, allow_hyphen_values = true)]
        lease: Option<f64>,
        /// Seconds without progress after which a task fails.
        #[arg(long, allow_hyphen_values = true)]
        stall: Option<f64>,
        /// Where robots meet when exploration is done, x,y.
        #[arg(long, value_parser = parse_point, allow_hyphen_values = true)]
        rendezvous: Option<pb::Point>,
    },
    /// Robots hold where they are until resumed.
    Pause {
        mission: u64,
        #[arg(long, default_value = "")]
        reason: String,
    },
    /// Robots get targets again.
    Resume {
        mission: u64,
        #[arg(long, default_value = "")]
        reason: String,
    },
    /// Delete a completed or paused mission with its robots, tasks, map and
    /// history; its place among the executive's missions is freed.
    Delete {
        mission: u64,
        #[arg(long, default_value = "")]
        reason: String,
    },
    /// Show the policy, or switch to another one while the mission runs.
    Policy {
        mission: u64,
        name: Option<String>,
        #[arg(long = "param", value_parser = parse_param)]
        params: Vec<(String, f64)>,
        #[arg(long, default_value = "")]
        reason: String,
    },
}

#[derive(Debug, Clone, Subcommand)]
pub(crate) enum OverrideAction {
    /// Go to a point x,y (metres); done on arrival.
    Goto {
        #[arg(value_parser = parse_point, allow_hyphen_values = true)]
        point: pb::Point,
    },
    /// Explore a rectangle x0,y0,x1,y1; done when no reachable frontier is left inside.
    Region {
        #[arg(value_parser = parse_rect, allow_hyphen_values = true)]
        area: pb::Rect,
    },
    /// Explore the frontier at x,y; other robots stay away from it meanwhile.
    Pin {
        #[arg(value_parser = parse_point, allow_hyphen_values = true)]
        point: pb::Point,
    },
    /// Stay put until released.
    Hold,
    /// Go to its start pose (or the rendezvous).
    Home,
    /// End its current task and hand it back to the policy.
    Release,
    /// Cancel its override and hand it back to the policy.
    Cancel,
}

fn numbers<const N: usize>(text: &str, what: &str) -> Result<[f64; N], String> {
    let values: Vec<f64> = text
        .split(',')
        .map(|part| part.trim().parse::<f64>())
        .collect::<Result<_, _>>()
        .map_err(|_| format!("`{text}` is not {what}"))?;
    // Checked here: ordering a rectangle's corners would turn NaN into the
    // other corner's value, and the executive would never see it.
    if let Some(odd) = values.iter().find(|v| !v.is_finite()) {
        return Err(format!("`{text}` holds {odd}; give finite numbers, {what}"));
    }
    values.try_into().map_err(|_| format!("`{text}` is not {what}"))
}

pub(crate) fn parse_point(text: &str) -> Result<pb::Point, String> {
    let [x, y] = numbers::<2>(text, "x,y in metres")?;
    Ok(pb::Point { x, y })
}

pub(crate) fn parse_rect(text: &str) -> Result<pb::Rect, String> {
    let [x0, y0, x1, y1] = numbers::<4>(text, "x0,y0,x1,y1 in metres")?;
    Ok(pb::Rect { min_x: x0.min(x1), min_y: y0.min(y1), max_x: x0.max(x1), max_y: y0.max(y1) })
}

pub(crate) fn parse_param(text: &str) -> Result<(String, f64), String> {
    let (name, value) = text.split_once('=').ok_or_else(|| format!("`{text}` is not name=value"))?;
    let value = value.trim().parse().map_err(|_| format!("`{value}` in `{text}` is not a number"))?;
    Ok((name.trim().to_owned(), value))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn points_and_rectangles_parse_and_rectangles_are_normalized() {
        let p = parse_point("1.5,-2").unwrap();
        assert_eq!((p.x, p.y), (1.5, -2.0));
        let r = parse_rect("4,3,1,-1").unwrap();
        assert_eq!((r.min_x, r.min_y, r.max_x, r.max_y), (1.0, -1.0, 4.0, 3.0));
        assert!(parse_point("1,2,3").is_err());
        assert!(parse_rect("a,b,c,d").is_err());
        assert_eq!(
            parse_rect("NaN,0,1,1").unwrap_err(),
            "`NaN,0,1,1` holds NaN; give finite numbers, x0,y0,x1,y1 in metres"
        );
        assert!(parse_point("inf,0").is_err());
        assert_eq!(parse_param("beta=2").unwrap(), ("beta".into(), 2.0));
        assert!(parse_param("beta").is_err());
    }

    /// Map origins and rendezvous points are often negative, and a
    /// negative lease is the executive's to refuse by name: none of them is
    /// taken for an option.
    #[test]
    fn negative_values_are_values() {
        let line = "coordctl missions create --width 10 --height 10 --origin -5.5,-3 --rendezvous -1,-2 \
                    --lease -1 --stall -2 --resolution -0.1";
        let cli = Cli::try_parse_from(line.split_whitespace()).unwrap();
        let Command::Missions {
            command: Some(MissionCommand::Create { origin, rendezvous, lease, stall, resolution, .. }),
        } = cli.command
        else {
            panic!("{:?}", cli.command)
        };
        let (origin, rendezvous) = (origin.unwrap(), rendezvous.unwrap());
        assert_eq!((origin.x, origin.y, rendezvous.x, rendezvous.y), (-5.5, -3.0, -1.0, -2.0));
        assert_eq!((lease, stall, resolution), (Some(-1.0), Some(-2.0), Some(-0.1)));
    }

    #[test]
    fn the_command_line_is_consistent() {
        use clap::CommandFactory;
        Cli::command().debug_assert();
    }
}
