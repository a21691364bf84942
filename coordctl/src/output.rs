//! Tables for people, JSON for scripts.

use std::collections::HashMap;

use serde_json::{Value, json};

use client_sim::console::StdoutError;
use client_sim::outln;
use exploration_proto::v1 as pb;

/// Leftover clusters a mission's text shows one by one, the largest; `--json` has all that were listed.
const LEFTOVERS_SHOWN: usize = 10;

/// Whether a result reached standard output.
pub type Printed = Result<(), StdoutError>;

/// Where results go, and in what form.
#[derive(Debug, Clone, Copy)]
pub struct Output {
    pub json: bool,
}

impl Output {
    pub fn missions(&self, missions: &[pb::Mission]) -> Printed {
        if self.json {
            return print_json(Value::Array(missions.iter().map(mission_json).collect()));
        }
        let mut table = Table::new(&["ID", "NAME", "STATE", "POLICY", "ROBOTS", "FRONTIER", "KNOWN", "REPLANS"]);
        for m in missions {
            table.row(vec![
                m.id.to_string(),
                m.name.clone(),
                mission_state(m.state()),
                m.policy.as_ref().map(|p| p.name.clone()).unwrap_or_default(),
                m.robots.to_string(),
                m.frontier_cells.to_string(),
                m.known_cells.to_string(),
                m.replans.to_string(),
            ]);
        }
        table.print()
    }

    pub fn mission(&self, m: &pb::Mission) -> Printed {
        if self.json {
            return print_json(mission_json(m));
        }
        let frame = m.frame.unwrap_or_default();
        let origin = frame.origin.unwrap_or_default();
        let lifecycle = m.lifecycle.unwrap_or_default();
        outln!("mission {} `{}`: {}", m.id, m.name, mission_state(m.state()))?;
        outln!("  policy      {}", policy_text(m.policy.as_ref()))?;
        outln!(
            "  frame       {} x {} cells of {} m from ({}, {})",
            frame.width,
            frame.height,
            frame.resolution,
            origin.x,
            origin.y
        )?;
        outln!("  robots      {}", m.robots)?;
        outln!("  map         {} known cells, {} frontier cells", m.known_cells, m.frontier_cells)?;
        if m.given_segmentation {
            outln!("  rooms       given (the segmentation policy plans on them; `rooms {} --online` undoes)", m.id)?;
        }
        outln!("  activity    {} map updates, {} replannings", m.map_updates, m.replans)?;
        outln!(
            "  lifecycle   lease {} s, stall {} s, rendezvous {}",
            lifecycle.lease_s,
            lifecycle.stall_s,
            lifecycle.rendezvous.map_or("each robot's start".into(), |p| point_text(Some(p)))
        )?;
        if m.scoped_by_communication {
            outln!("  coordinated per connected sub-team (limited communication)")?;
        }
        for region in &m.forbidden_regions {
            outln!("  forbidden   #{} {} by {} ({})", region.id, rect_text(region.area), region.actor, region.reason)?;
        }
        for left in m.leftovers.iter().take(LEFTOVERS_SHOWN) {
            outln!(
                "  left over   {} frontier cells near {}: {}",
                left.cells,
                point_text(left.position),
                leftover_reason(left.reason())
            )?;
        }
        let rest = m.leftovers.get(LEFTOVERS_SHOWN..).unwrap_or_default();
        let more = rest.len() as u64 + m.unlisted_leftovers;
        if more > 0 {
            let cells = rest.iter().map(|l| l.cells).sum::<u64>() + m.unlisted_leftover_cells;
            outln!("  left over   {more} more clusters, {cells} frontier cells among them")?;
        }
        Ok(())
    }

    pub fn policy(&self, m: &pb::Mission) -> Printed {
        if self.json {
            return print_json(json!({ "mission_id": m.id, "policy": policy_json(m.policy.as_ref()) }));
        }
        outln!("mission {}: {}", m.id, policy_text(m.policy.as_ref()))
    }

    pub fn policies(&self, policies: &[pb::PolicyInfo]) -> Printed {
        if self.json {
            let list = policies
                .iter()
                .map(|p| {
                    let params: Vec<Value> = p
                        .params
                        .iter()
                        .map(|q| json!({"name": q.name, "description": q.description, "default": q.default_value, "min": q.min, "max": q.max}))
                        .collect();
                    json!({ "name": p.name, "description": p.description, "params": params })
                })
                .collect();
            return print_json(Value::Array(list));
        }
        for p in policies {
            outln!("{:<14}{}", p.name, p.description)?;
            for q in &p.params {
                outln!("    {:<24}{} (default {}, {} ..= {})", q.name, q.description, q.default_value, q.min, q.max)?;
            }
        }
        Ok(())
    }

    pub fn robots(&self, robots: &[pb::Robot]) -> Printed {
        if self.json {
            return print_json(Value::Array(robots.iter().map(robot_json).collect()));
        }
        let mut table = Table::new(&["ID", "NAME", "STATE", "TASK", "KIND", "TARGET", "POSE", "SEEN", "TRAVELLED"]);
        for r in robots {
            let state = if r.lost { "LOST".to_owned() } else { robot_state(r.state()) };
            let pose = r.pose.unwrap_or_default();
            table.row(vec![
                r.id.to_string(),
                r.name.clone(),
                state,
                if r.task_id == 0 { "-".into() } else { r.task_id.to_string() },
                if r.task_id == 0 { "-".into() } else { task_kind(r.task_kind()) },
                point_text(r.target),
                format!("({:.2}, {:.2})", pose.x, pose.y),
                r.last_seen.map_or("never".into(), |t| t.to_string()),
                format!("{:.1} m", r.distance_m),
            ]);
        }
        table.print()
    }

    pub fn tasks(&self, tasks: &[pb::Task], names: &HashMap<u64, String>, history: bool) -> Printed {
        let name = |id: u64| names.get(&id).cloned().unwrap_or_else(|| id.to_string());
        if self.json {
            return print_json(Value::Array(tasks.iter().map(|t| task_json(t, &name(t.robot_id))).collect()));
        }
        let mut table = Table::new(&["TASK", "ROBOT", "KIND", "STATE", "TARGET", "BY", "CREATED", "NOTE"]);
        for t in tasks {
            table.row(vec![
                t.id.to_string(),
                name(t.robot_id),
                task_kind(t.kind()),
                task_state(t.state()),
                point_text(t.target),
                t.created_by.clone(),
                t.created_at.map(|t| t.to_string()).unwrap_or_default(),
                t.note.clone(),
            ]);
            if history {
                for step in &t.transitions {
                    let who =
                        if step.by.is_empty() { step.actor.clone() } else { format!("{} {}", step.actor, step.by) };
                    table.row(vec![
                        String::new(),
                        String::new(),
                        String::new(),
                        format!("-> {}", task_state(step.to())),
                        String::new(),
                        who,
                        step.at.map(|t| t.to_string()).unwrap_or_default(),
                        step.cause.clone(),
                    ]);
                }
            }
        }
        table.print()
    }

    pub fn events(&self, events: &[pb::MissionEvent]) -> Printed {
        if self.json {
            let list = events
                .iter()
                .map(|e| json!({"id": e.id, "at": e.at.map(|t| t.to_string()), "kind": e.kind, "detail": e.detail, "actor": e.actor}))
                .collect();
            return print_json(Value::Array(list));
        }
        let mut table = Table::new(&["ID", "AT", "KIND", "BY", "DETAIL"]);
        for e in events {
            let at = e.at.map(|t| t.to_string()).unwrap_or_default();
            table.row(vec![e.id.to_string(), at, e.kind.clone(), e.actor.clone(), e.detail.clone()]);
        }
        table.print()
    }

    pub fn regions(&self, regions: &[pb::Region]) -> Printed {
        if self.json {
            return print_json(Value::Array(regions.iter().map(region_json).collect()));
        }
        for r in regions {
            outln!("region #{} of mission {}: {} forbidden by {}", r.id, r.mission_id, rect_text(r.area), r.actor)?;
        }
        Ok(())
    }

    pub fn view(&self, view: &pb::MissionView) -> Printed {
        let Some(m) = &view.mission else { return Ok(()) };
        if self.json {
            let robots: Vec<Value> = view.robots.iter().map(robot_json).collect();
            return outln!("{}", json!({ "mission": mission_json(m), "robots": robots }));
        }
        let robots: Vec<String> = view
            .robots
            .iter()
            .map(|r| {
                let doing = if r.lost {
                    "lost".to_owned()
                } else if r.task_id == 0 {
                    "idle".to_owned()
                } else {
                    format!("{}->{}", task_kind(r.task_kind()), point_text(r.target))
                };
                format!("{} {doing}", r.name)
            })
            .collect();
        outln!(
            "{} {} frontier={} known={} replans={} | {}",
            prost_types::Timestamp::from(std::time::SystemTime::now()),
            mission_state(m.state()),
            m.frontier_cells,
            m.known_cells,
            m.replans,
            robots.join(", ")
        )
    }

    pub fn done(&self, what: &str) -> Printed {
        if self.json { print_json(json!({ "done": what })) } else { outln!("{what}") }
    }
}

fn print_json(value: Value) -> Printed {
    outln!("{}", serde_json::to_string_pretty(&value).expect("JSON values serialize"))
}

/// Columns padded to their widest cell.
struct Table {
    rows: Vec<Vec<String>>,
}

impl Table {
    fn new(header: &[&str]) -> Self {
        Self { rows: vec![header.iter().map(|h| (*h).to_owned()).collect()] }
    }

    fn row(&mut self, cells: Vec<String>) {
        self.rows.push(cells);
    }

    fn print(&self) -> Printed {
        let columns = self.rows[0].len();
        let widths: Vec<usize> =
            (0..columns).map(|c| self.rows.iter().map(|r| r[c].chars().count()).max().unwrap_or(0)).collect();
        for row in &self.rows {
            let line: Vec<String> = row.iter().zip(&widths).map(|(cell, w)| format!("{cell:<w$}")).collect();
            outln!("{}", line.join("  ").trim_end())?;
        }
        Ok(())
    }
}

fn point_text(p: Option<pb::Point>) -> String {
    p.map_or("-".into(), |p| format!("({:.2}, {:.2})", p.x, p.y))
}

fn rect_text(r: Option<pb::Rect>) -> String {
    let r = r.unwrap_or_default();
    format!("[{:.2}, {:.2}] x [{:.2}, {:.2}]", r.min_x, r.max_x, r.min_y, r.max_y)
}

fn policy_text(p: Option<&pb::PolicySpec>) -> String {
    let Some(p) = p else { return "-".into() };
    let mut params: Vec<String> = p.params.iter().map(|(k, v)| format!("{k}={v}")).collect();
    params.sort();
    if params.is_empty() { p.name.clone() } else { format!("{} ({})", p.name, params.join(", ")) }
}

fn point_json(p: Option<pb::Point>) -> Value {
    p.map_or(Value::Null, |p| json!({ "x": p.x, "y": p.y }))
}

fn rect_json(r: Option<pb::Rect>) -> Value {
    r.map_or(Value::Null, |r| json!({ "min_x": r.min_x, "min_y": r.min_y, "max_x": r.max_x, "max_y": r.max_y }))
}

fn policy_json(p: Option<&pb::PolicySpec>) -> Value {
    p.map_or(Value::Null, |p| json!({ "name": p.name, "params": p.params }))
}

fn region_json(r: &pb::Region) -> Value {
    json!({ "id": r.id, "mission_id": r.mission_id, "area": rect_json(r.area), "actor": r.actor, "reason": r.reason })
}

fn mission_json(m: &pb::Mission) -> Value {
    let frame = m.frame.unwrap_or_default();
    let lifecycle = m.lifecycle.unwrap_or_default();
    let leftovers: Vec<Value> = m
        .leftovers
        .iter()
        .map(|l| json!({ "reason": leftover_reason(l.reason()), "cells": l.cells, "position": point_json(l.position) }))
        .collect();
    json!({
        "id": m.id,
        "name": m.name,
        "state": mission_state(m.state()),
        "policy": policy_json(m.policy.as_ref()),
        "frame": { "resolution": frame.resolution, "origin": point_json(frame.origin), "width": frame.width, "height": frame.height },
        "robots": m.robots,
        "known_cells": m.known_cells,
        "frontier_cells": m.frontier_cells,
        "replans": m.replans,
        "map_updates": m.map_updates,
        "scoped_by_communication": m.scoped_by_communication,
        "lifecycle": { "lease_s": lifecycle.lease_s, "stall_s": lifecycle.stall_s, "rendezvous": point_json(lifecycle.rendezvous) },
        "given_segmentation": m.given_segmentation,
        "forbidden_regions": m.forbidden_regions.iter().map(region_json).collect::<Vec<_>>(),
        "leftovers": leftovers,
        "unlisted_leftovers": { "clusters": m.unlisted_leftovers, "cells": m.unlisted_leftover_cells },
    })
}

fn robot_json(r: &pb::Robot) -> Value {
    let pose = r.pose.unwrap_or_default();
    json!({
        "id": r.id,
        "mission_id": r.mission_id,
        "name": r.name,
        "state": robot_state(r.state()),
        "lost": r.lost,
        "task_id": r.task_id,
        "task_kind": task_kind(r.task_kind()),
        "target": point_json(r.target),
        "pose": { "x": pose.x, "y": pose.y, "theta": pose.theta },
        "home": point_json(r.home),
        "last_seen": r.last_seen.map(|t| t.to_string()),
        "distance_m": r.distance_m,
        "blacklisted": r.blacklisted,
    })
}

fn task_json(t: &pb::Task, robot: &str) -> Value {
    let transitions: Vec<Value> = t
        .transitions
        .iter()
        .map(|s| {
            json!({
                "from": task_state(s.from()),
                "to": task_state(s.to()),
                "at": s.at.map(|t| t.to_string()),
                "cause": s.cause,
                "actor": s.actor,
                "by": s.by,
            })
        })
        .collect();
    json!({
        "id": t.id,
        "robot_id": t.robot_id,
        "robot": robot,
        "kind": task_kind(t.kind()),
        "state": task_state(t.state()),
        "target": point_json(t.target),
        "policy": t.policy,
        "utility": t.utility,
        "path_cost": t.path_cost,
        "created_by": t.created_by,
        "note": t.note,
        "created_at": t.created_at.map(|t| t.to_string()),
        "transitions": transitions,
    })
}

/// A proto enum value's name without its type's prefix, in lower case
/// (`TASK_STATE_ACTIVE` → `active`).
fn short(name: &str) -> String {
    ["MISSION_STATE_", "ROBOT_STATE_", "TASK_KIND_", "TASK_STATE_"]
        .iter()
        .find_map(|prefix| name.strip_prefix(prefix))
        .unwrap_or(name)
        .to_lowercase()
}

fn mission_state(s: pb::MissionState) -> String {
    short(s.as_str_name())
}

fn robot_state(s: pb::RobotState) -> String {
    short(s.as_str_name())
}

fn task_kind(k: pb::TaskKind) -> String {
    short(k.as_str_name())
}

fn task_state(s: pb::TaskState) -> String {
    short(s.as_str_name())
}

fn leftover_reason(r: pb::LeftoverReason) -> &'static str {
    match r {
        pb::LeftoverReason::Unspecified => "unknown",
        pb::LeftoverReason::TooNarrow => "too narrow for every robot",
        pb::LeftoverReason::Disconnected => "not connected to any robot",
        pb::LeftoverReason::Blacklisted => "blacklisted (unreachable or stalled)",
        pb::LeftoverReason::Forbidden => "inside a forbidden region",
        pb::LeftoverReason::TooSmall => "smaller than the minimum frontier",
    }
}
