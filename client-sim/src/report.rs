//! `docs/results.md`: for each experiment, the paper's claim, the setting we
//! ran, our figures and plots, and whether our results agree, computed from
//! the runs (the paired t-test over seeds at 95 %) and followed by the
//! experiment's notes.

use std::collections::BTreeMap;
use std::fmt::Write as _;
use std::path::Path;

use crate::experiment::{CheckSpec, Experiment, ExperimentError};
use crate::runs::{Row, read_runs, samples};
use crate::stats::{Sample, paired, welch};

/// Where experiments keep their runs unless told otherwise: one folder per
/// experiment, named after it.
pub const DEFAULT_RESULTS: &str = "docs/results";

/// The verdict on one claim.
#[derive(Debug, Clone, PartialEq)]
pub struct Verdict {
    /// "agrees", "partly agrees", "disagrees".
    pub word: &'static str,
    /// The figures behind it, one line per cell tested.
    pub lines: Vec<String>,
}

type Data = BTreeMap<(String, String, usize, String), Sample>;

/// One figure per run, keyed by (world index, seed).
type RunsByWorldSeed = BTreeMap<(usize, u64), f64>;

/// Tests one claim on the results.
pub fn check(experiment: &Experiment, spec: &CheckSpec, data: &Data) -> Verdict {
    if spec.kind == "beats_best" {
        return check_best(experiment, spec, data);
    }
    let comm = spec
        .comm_range
        .clone()
        .or_else(|| experiment.comm_ranges.first().cloned())
        .unwrap_or_else(|| "unlimited".into());
    let worlds: Vec<String> = if spec.worlds.is_empty() {
        experiment.worlds.iter().map(|w| w.name.clone()).collect()
    } else {
        spec.worlds.clone()
    };
    let robots: Vec<usize> = if spec.robots.is_empty() {
        experiment.robots.iter().copied().filter(|&n| n > 1).collect()
    } else {
        spec.robots.clone()
    };
    let (mut supporting, mut opposing, mut tested, mut gains) = (0, 0, 0, Vec::new());
    let mut lines = Vec::new();
    for world in &worlds {
        for &n in &robots {
            let key = |l: &str| (world.clone(), l.to_owned(), n, comm.clone());
            let (Some(better), Some(worse)) = (data.get(&key(&spec.better)), data.get(&key(&spec.worse))) else {
                continue;
            };
            tested += 1;
            // A seed gives both the same world and start: pair by seed when
            // the runs share seeds, else compare the samples (Welch).
            let (difference, half, significant, test) = match paired(better, worse) {
                Some((d, h, s, pairs)) => (d, h, s, format!("paired over {pairs} seeds")),
                None => {
                    let (d, h, s) = welch(better, worse);
                    (d, h, s, "Welch".to_owned())
                }
            };
            let gain = -100.0 * difference / worse.mean();
            gains.push(gain);
            let holds = match spec.kind.as_str() {
                "similar" => !significant,
                _ => significant && difference < 0.0,
            };
            if holds {
                supporting += 1;
            } else if spec.kind != "similar" && significant && difference > 0.0 {
                opposing += 1;
            }
            // Seconds need a decimal: runs take a few of them.
            let digits = if spec.metric.ends_with("_s") { 1 } else { 0 };
            lines.push(format!(
                "{world}, {n} robots: {} {:.*} vs {} {:.*} {} {}",
                spec.better,
                digits,
                better.mean(),
                spec.worse,
                digits,
                worse.mean(),
                spec.metric,
                difference_text(gain, 100.0 * half / worse.mean(), &test, significant)
            ));
        }
    }
    let word = if tested == 0 {
        "not tested"
    } else if spec.kind == "gain" {
        let mean_gain = gains.iter().sum::<f64>() / gains.len() as f64;
        lines.push(format!(
            "mean gain of {} over {}: {mean_gain:.1} %{}",
            spec.better,
            spec.worse,
            spec.expected_gain.map_or(String::new(), |g| format!(" (paper: {g:.0} %)"))
        ));
        match spec.expected_gain {
            Some(g) if mean_gain > 0.0 && mean_gain >= g / 2.0 => "agrees",
            Some(_) if mean_gain > 0.0 => "partly agrees",
            None if mean_gain > 0.0 => "agrees",
            _ => "disagrees",
        }
    } else if supporting * 2 >= tested && opposing == 0 {
        "agrees"
    } else if supporting > 0 {
        "partly agrees"
    } else {
        "disagrees"
    };
    Verdict { word, lines }
}

/// "(−12.3 % ± 4.5, paired over 20 seeds), significant": a gain in per
/// cent (shown as fewer, "−", or more, "+"), its 95 % half-width, the test,
/// and whether the difference is significant.
fn difference_text(gain: f64, half_percent: f64, test: &str, significant: bool) -> String {
    format!(
        "({}{:.1} % ± {half_percent:.1}, {test}), {}",
        if gain >= 0.0 { "−" } else { "+" },
        gain.abs(),
        if significant { "significant" } else { "not significant" }
    )
}

/// `beats_best`: per team size, `better` against the best of `against`,
/// over the checked worlds together. The best is the label with the lowest
/// mean over those worlds and seeds (chosen per team size, not per world);
/// the test pairs runs of one world and one seed, which share the world and
/// the start.
fn check_best(experiment: &Experiment, spec: &CheckSpec, data: &Data) -> Verdict {
    let comm = spec.comm_range.clone().unwrap_or_else(|| "unlimited".into());
    let worlds: Vec<String> = if spec.worlds.is_empty() {
        experiment.worlds.iter().map(|w| w.name.clone()).collect()
    } else {
        spec.worlds.clone()
    };
    let against: Vec<String> = if spec.against.is_empty() {
        experiment.policies.iter().map(|p| if p.label.is_empty() { p.name.clone() } else { p.label.clone() }).collect()
    } else {
        spec.against.clone()
    };
    let robots: Vec<usize> = if spec.robots.is_empty() { experiment.robots.clone() } else { spec.robots.clone() };
    // Each run keyed by (world, seed): a seed gives every policy the same world and start.
    let runs_of = |label: &str, n: usize| -> RunsByWorldSeed {
        worlds
            .iter()
            .enumerate()
            .filter_map(|(w, world)| data.get(&(world.clone(), label.to_owned(), n, comm.clone())).map(|s| (w, s)))
            .flat_map(|(w, s)| s.seeded_values().filter_map(move |(seed, v)| Some(((w, seed?), v))))
            .collect()
    };
    let expected = spec.expected_gain.unwrap_or(0.0);
    let (mut holding, mut tested, mut lines) = (0, 0, Vec::new());
    for n in robots {
        let ours = runs_of(&spec.better, n);
        let others: Vec<(&String, RunsByWorldSeed)> = against
            .iter()
            .filter(|l| **l != spec.better)
            .map(|l| (l, runs_of(l, n)))
            .filter(|(_, runs)| !runs.is_empty())
            .collect();
        // Compare on the runs every policy has, so that means are of one set.
        let common: Vec<(usize, u64)> =
            ours.keys().copied().filter(|k| others.iter().all(|(_, runs)| runs.contains_key(k))).collect();
        let sample = |runs: &RunsByWorldSeed| {
            Sample::seeded(common.iter().map(|&(w, seed)| (w as u64 * 1_000_000 + seed, runs[&(w, seed)])).collect())
        };
        let best = others.iter().map(|(l, runs)| (*l, sample(runs))).min_by(|a, b| a.1.mean().total_cmp(&b.1.mean()));
        let Some((label, best)) = best else { continue };
        let ours = sample(&ours);
        let Some((difference, half, significant, pairs)) = paired(&ours, &best) else { continue };
        tested += 1;
        let gain = -100.0 * difference / best.mean();
        let holds = if expected > 0.0 { significant && gain >= expected } else { !(significant && difference > 0.0) };
        holding += usize::from(holds);
        let worlds_run = common.iter().map(|(w, _)| w).collect::<std::collections::BTreeSet<_>>().len();
        lines.push(format!(
            "{n} robots: {} {:.0} vs the best of the others, {label}, {:.0} {} {}",
            spec.better,
            ours.mean(),
            best.mean(),
            spec.metric,
            difference_text(
                gain,
                100.0 * half / best.mean(),
                &format!("paired over {pairs} runs in {worlds_run} worlds"),
                significant
            )
        ));
    }
    let word = match (holding, tested) {
        (_, 0) => "not tested",
        (h, t) if h == t => "agrees",
        (0, _) => "disagrees",
        _ => "partly agrees",
    };
    Verdict { word, lines }
}

/// Writes the results report for `experiments` (each with its results folder)
/// to `out`. `results` is the folder holding the experiments' folders, as the
/// user named it: the report says where its runs are and how to make them
/// again.
pub fn write_report(
    experiments: &[(Experiment, std::path::PathBuf)],
    results: &Path,
    out: &Path,
) -> Result<(), ExperimentError> {
    let root = out.parent().unwrap_or(Path::new("."));
    let mut md = String::new();
    let _ = writeln!(md, "# Results: the papers' experiments, reproduced through the real service\n");
    let _ = writeln!(
        md,
        "Generated by `fleet-sim report` from the runs in `{}/` (see the end for the commands). Every run \
         is a real mission against an executive over gRPC, with the simulator's models at the papers' values \
         unless stated: 15 cm cells, 360° sensors of 4 m, interference (a move near another robot within 1 m \
         succeeds with probability 0.7), the team packed one robot per cell around one random start, time in simulated seconds. Figures are means over seeds with \
         95 % confidence intervals; \"significant\" is the paired t-test over seeds at 5 % (a seed gives every \
         policy the same world and start), or Welch's t-test where runs share no seeds.\n",
        results.display()
    );
    if experiments.iter().any(|(e, _)| e.notes.trim_start_matches('*').starts_with("Not yet re-run")) {
        let _ = writeln!(
            md,
            "An experiment whose notes begin \"Not yet re-run\" was made with an earlier simulator; its notes say \
             how it differed.\n"
        );
    }
    for (experiment, dir) in experiments {
        let rows = read_runs(dir)?;
        let ok = rows.iter().filter(|r| r.get("status").map(String::as_str) == Some("ok")).count();
        let failed = rows.len() - ok;
        let completed = rows.iter().filter(|r| r.get("completed").map(String::as_str) == Some("true")).count();
        // A fold from +0, not `sum`, whose empty sum is -0 ("-0 s of run time").
        let wall = rows.iter().filter_map(|r| r.get("wall_time_s")?.parse::<f64>().ok()).fold(0.0, |a, b| a + b);
        let seeds = seeds_done(experiment, &rows);
        let _ = writeln!(md, "## {} — `{}`\n", experiment.paper, experiment.name);
        let _ = writeln!(md, "**Claim.** {}\n", experiment.claim);
        let worlds: Vec<String> = experiment
            .worlds
            .iter()
            .map(|w| match (&w.map, &w.generator) {
                (Some(m), _) => {
                    format!("{} (`{}`)", w.name, m.trim_start_matches("$SHARED/").trim_start_matches("../"))
                }
                (None, Some(g)) => format!("{} (generated {g}, {} × {} m)", w.name, w.width_m, w.height_m),
                _ => w.name.clone(),
            })
            .collect();
        let policies: Vec<String> = experiment
            .policies
            .iter()
            .map(|p| {
                let label = if p.label.is_empty() { &p.name } else { &p.label };
                if p.params.is_empty() {
                    format!("`{label}`")
                } else {
                    format!("`{label}` ({} {:?})", p.name, p.params)
                }
            })
            .collect();
        let sim = &experiment.sim;
        let _ = writeln!(
            md,
            "**Setting.** Worlds: {}. Robots: {:?}. Policies: {}. {}. Cells {} m, sensor {} m / {}°, \
             interference {}, start {} ({}).{} Runs: {} done ({} completed the map, {} failed or timed out; time \
             limit {} s), {:.0} s of run time in all.\n",
            worlds.join(", "),
            experiment.robots,
            policies.join(", "),
            seeds,
            sim.cell_size,
            sim.sensor_range,
            sim.fov,
            if sim.interference < 1.0 { format!("p = {}", sim.interference) } else { "off".into() },
            sim.start,
            sim.layout,
            if experiment.comm_ranges.is_empty() {
                String::new()
            } else {
                format!(" Communication ranges: {}.", experiment.comm_ranges.join(", "))
            },
            rows.len(),
            completed,
            failed,
            experiment.time_limit_s,
            wall
        );
        // The figures: exploration time per cell.
        let data = samples(&rows, "steps");
        let labels: Vec<String> = experiment
            .policies
            .iter()
            .map(|p| if p.label.is_empty() { p.name.clone() } else { p.label.clone() })
            .collect();
        let ranges = if experiment.comm_ranges.is_empty() {
            vec!["unlimited".to_owned()]
        } else {
            experiment.comm_ranges.clone()
        };
        for world in &experiment.worlds {
            for comm in &ranges {
                let _ = writeln!(
                    md,
                    "Exploration time (steps), {}{}:\n",
                    world.name,
                    if comm == "unlimited" { String::new() } else { format!(", communication range {comm}") }
                );
                let _ = writeln!(md, "| robots | {} |", labels.join(" | "));
                let _ = writeln!(md, "|---|{}", "---|".repeat(labels.len()));
                for &n in &experiment.robots {
                    let cells: Vec<String> = labels
                        .iter()
                        .map(|l| {
                            data.get(&(world.name.clone(), l.clone(), n, comm.clone()))
                                .map_or("–".into(), |s| format!("{:.0} ± {:.0}", s.mean(), s.ci95()))
                        })
                        .collect();
                    let _ = writeln!(md, "| {n} | {} |", cells.join(" | "));
                }
                let _ = writeln!(md);
            }
        }
        for figure in &experiment.tables {
            let values = samples(&rows, figure);
            let _ = writeln!(md, "`{figure}` (mean ± 95 % CI):\n");
            let _ = writeln!(md, "| world | robots | {} |", labels.join(" | "));
            let _ = writeln!(md, "|---|---|{}", "---|".repeat(labels.len()));
            for world in &experiment.worlds {
                for &n in &experiment.robots {
                    let cells: Vec<String> = labels
                        .iter()
                        .map(|l| {
                            values
                                .get(&(world.name.clone(), l.clone(), n, "unlimited".to_owned()))
                                .map_or("–".into(), |s| format!("{:.2} ± {:.2}", s.mean(), s.ci95()))
                        })
                        .collect();
                    let _ = writeln!(md, "| {} | {n} | {} |", world.name, cells.join(" | "));
                }
            }
            let _ = writeln!(md);
        }
        for spec in &experiment.checks {
            let metric_data = samples(&rows, &spec.metric);
            let verdict = check(experiment, spec, &metric_data);
            let _ = writeln!(md, "**{}** — our result **{}**:\n", spec.claim, verdict.word);
            for line in &verdict.lines {
                let _ = writeln!(md, "- {line}");
            }
            let _ = writeln!(md);
        }
        let mut plots: Vec<_> = std::fs::read_dir(dir)
            .map(|d| d.filter_map(|e| e.ok()).map(|e| e.path()).collect::<Vec<_>>())
            .unwrap_or_default()
            .into_iter()
            .filter(|p| p.extension().is_some_and(|e| e == "png"))
            .collect();
        plots.sort();
        for plot in plots {
            let relative = plot.strip_prefix(root).unwrap_or(&plot);
            let _ = writeln!(md, "![{}]({})\n", relative.display(), relative.display());
        }
        let pictures = dir.join("pictures");
        if let Ok(entries) = std::fs::read_dir(&pictures) {
            let mut pics: Vec<_> = entries.filter_map(|e| e.ok()).map(|e| e.path()).collect();
            pics.sort();
            if let Some(first) = pics.first() {
                let relative = first.strip_prefix(root).unwrap_or(first);
                let _ = writeln!(
                    md,
                    "One run (seed 1), each robot's trajectory in its own colour, starts as discs, ends as squares: \
                     ![run]({})  \nAll of them are in `{}`.\n",
                    relative.display(),
                    pictures.strip_prefix(root).unwrap_or(&pictures).display()
                );
            }
        }
        if !experiment.notes.trim().is_empty() {
            let _ = writeln!(md, "**Notes.** {}\n", experiment.notes.trim());
        }
    }
    // The experiments of this report, in its order (configs are named after them).
    let names: Vec<&str> = experiments.iter().map(|(e, _)| e.name.as_str()).collect();
    let configs: Vec<String> = names.iter().map(|n| format!("experiments/{n}.toml")).collect();
    let _ = writeln!(
        md,
        "## Regenerating\n\n```sh\ncargo build --release -p client-sim\nfor e in {}; do\n  \
         target/release/fleet-sim experiment --config experiments/$e.toml --out {results}/$e\ndone\n\
         target/release/fleet-sim report --out {}{} {}\n```\n\n\
         Experiments over the shared maps need `EXPLORATION_SHARED_MAPS`; an interrupted experiment resumes where \
         it stopped when run again with the same `--out`.\n",
        names.join(" "),
        out.display(),
        if results == Path::new(DEFAULT_RESULTS) { String::new() } else { format!(" --results {}", results.display()) },
        configs.join(" "),
        results = results.display(),
    );
    std::fs::write(out, md).map_err(|cause| ExperimentError::Io { path: out.to_owned(), cause })
}

/// Which seeds were run: all the planned ones, or (a run cut for time) the
/// first few, which cover every cell since runs go seed by seed.
fn seeds_done(experiment: &Experiment, rows: &[Row]) -> String {
    let cells = crate::experiment::matrix(experiment).len() / experiment.seeds.max(1) as usize;
    let runs_of = |seed: u64| rows.iter().filter(|r| r.get("seed").and_then(|s| s.parse().ok()) == Some(seed)).count();
    let complete = (1..=experiment.seeds).take_while(|&s| runs_of(s) >= cells).count() as u64;
    if complete == experiment.seeds {
        format!("Seeds 1–{} per cell", experiment.seeds)
    } else if complete == 0 {
        format!(
            "No seed complete of the {} planned per cell ({} of the {cells} cells have seed 1)",
            experiment.seeds,
            runs_of(1)
        )
    } else {
        let partial = runs_of(complete + 1);
        format!(
            "Seeds 1–{complete} per cell of the {} planned (cut for time; runs go seed by seed{})",
            experiment.seeds,
            if partial > 0 {
                format!(", and {partial} of the {cells} cells have seed {} too", complete + 1)
            } else {
                String::new()
            }
        )
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn experiment(check: &str) -> Experiment {
        toml::from_str(&format!(
            r#"
name = "t"
paper = "p"
claim = "c"
seeds = 6
robots = [2, 4]
[sim]
[[worlds]]
name = "small"
generator = "empty"
[[worlds]]
name = "large"
generator = "empty"
[[policies]]
name = "tours"
[[policies]]
name = "minpos"
[[policies]]
name = "greedy"
[[checks]]
{check}
"#
        ))
        .expect("a valid experiment")
    }

    /// Steps per seed 1..=6: `base` plus a seed-dependent wobble the same
    /// for every policy (a seed fixes world and start).
    fn runs(data: &mut Data, world: &str, label: &str, n: usize, base: f64) {
        let pairs = (1..=6).map(|s| (s, base + 7.0 * (s % 3) as f64 + 0.5 * (s % 2) as f64)).collect();
        data.insert((world.into(), label.into(), n, "unlimited".into()), Sample::seeded(pairs));
    }

    #[test]
    fn the_best_is_chosen_per_team_size_over_all_worlds_together() {
        let mut data = Data::new();
        // 2 robots: greedy wins the small world, minpos the two together
        // (100 + 200 against 90 + 260); tours beats minpos by 15 %.
        // 4 robots: tours less than 5 % better than the best (the wobble is
        // the same in steps, not in per cent).
        for (n, label, small, large) in [
            (2, "greedy", 90.0, 260.0),
            (2, "minpos", 100.0, 200.0),
            (2, "tours", 85.0, 170.0),
            (4, "greedy", 50.0, 100.0),
            (4, "minpos", 60.0, 120.0),
            (4, "tours", 47.5, 95.0),
        ] {
            runs(&mut data, "small", label, n, small);
            runs(&mut data, "large", label, n, large);
        }
        let spec = r#"claim = "x"
kind = "beats_best"
better = "tours"
expected_gain = 10"#;
        let e = experiment(spec);
        let verdict = check(&e, &e.checks[0], &data);
        assert_eq!(verdict.word, "partly agrees", "{verdict:?}");
        assert!(verdict.lines[0].starts_with("2 robots") && verdict.lines[0].contains("minpos"), "{verdict:?}");
        assert!(verdict.lines[0].contains("paired over 12 runs in 2 worlds"), "{verdict:?}");
        assert!(verdict.lines[1].contains("greedy") && verdict.lines[1].contains("−4.6 %"), "{verdict:?}");
        // Not significantly worse is all a gain of 0 asks.
        let e = experiment(&spec.replace("expected_gain = 10", "expected_gain = 0"));
        assert_eq!(check(&e, &e.checks[0], &data).word, "agrees");
        // Against greedy alone at 2 robots: 255 against 350, a gain of 27 %.
        let e = experiment(&format!("{spec}\nagainst = [\"greedy\"]\nrobots = [2]"));
        let verdict = check(&e, &e.checks[0], &data);
        assert_eq!(verdict.word, "agrees", "{verdict:?}");
    }
}
