//! An experiment's results folder: `runs.csv` (one row per run, every
//! setting and every figure, appended as runs finish) and `summary.csv`
//! (per cell of the matrix, mean ± 95 % CI of each figure), read and
//! written with the `csv` crate.

use std::collections::BTreeMap;
use std::path::Path;

use crate::experiment::config::{ExperimentError, io};
use crate::stats::Sample;

/// The columns of `runs.csv`.
pub const RUN_COLUMNS: [&str; 26] = [
    "id",
    "world",
    "policy",
    "label",
    "robots",
    "comm_range",
    "seed",
    "status",
    "error",
    "completed",
    "steps",
    "t50",
    "t90",
    "t95",
    "t100",
    "coverage",
    "distance_mean",
    "distance_max",
    "idle_steps",
    "overlap",
    "replans",
    "map_updates",
    "wall_time_s",
    "reachable_cells",
    "comm_range_m",
    "switches_per_100",
];

fn csv_error(path: &Path) -> impl Fn(csv::Error) -> ExperimentError + '_ {
    move |e| ExperimentError::Io { path: path.to_owned(), cause: std::io::Error::other(e) }
}

/// One row of `runs.csv`, by column name.
pub type Row = BTreeMap<String, String>;

/// Reads `runs.csv` of a results folder (none yet: no rows).
pub fn read_runs(dir: &Path) -> Result<Vec<Row>, ExperimentError> {
    let path = dir.join("runs.csv");
    if !path.exists() {
        return Ok(Vec::new());
    }
    let mut reader = csv::ReaderBuilder::new().flexible(true).from_path(&path).map_err(csv_error(&path))?;
    let header: Vec<String> = reader.headers().map_err(csv_error(&path))?.iter().map(str::to_owned).collect();
    reader
        .records()
        .map(|record| {
            let record = record.map_err(csv_error(&path))?;
            Ok(header.iter().cloned().zip(record.iter().map(str::to_owned)).collect())
        })
        .collect()
}

/// `runs.csv`, open for appending rows as runs finish.
#[derive(Debug)]
pub struct RunsFile {
    writer: csv::Writer<std::fs::File>,
    path: std::path::PathBuf,
}

impl RunsFile {
    /// Opens (or starts, with its header) the `runs.csv` of `dir`.
    pub fn open(dir: &Path) -> Result<Self, ExperimentError> {
        let path = dir.join("runs.csv");
        let file = std::fs::OpenOptions::new().create(true).append(true).open(&path).map_err(io(&path))?;
        let fresh = file.metadata().map_err(io(&path))?.len() == 0;
        let mut writer = csv::WriterBuilder::new().flexible(true).from_writer(file);
        if fresh {
            writer.write_record(RUN_COLUMNS).map_err(csv_error(&path))?;
            writer.flush().map_err(io(&path))?;
        }
        Ok(Self { writer, path })
    }

    /// Appends one run's row and flushes it to the file.
    pub fn append(&mut self, row: &[String]) -> Result<(), ExperimentError> {
        self.writer.write_record(row).map_err(csv_error(&self.path))?;
        self.writer.flush().map_err(io(&self.path))
    }
}

/// The cells of the matrix: (world, label, robots, comm).
pub type CellKey = (String, String, usize, String);

fn cell_of(row: &Row) -> CellKey {
    let field = |name: &str| row.get(name).cloned().unwrap_or_default();
    (field("world"), field("label"), field("robots").parse().unwrap_or(0), field("comm_range"))
}

fn metric(row: &Row, name: &str) -> Option<f64> {
    row.get(name).and_then(|v| v.parse().ok())
}

/// Groups the successful runs' figures by cell, each value with its seed
/// (for paired statistics).
pub fn samples(rows: &[Row], name: &str) -> BTreeMap<CellKey, Sample> {
    let mut out: BTreeMap<CellKey, Vec<(u64, f64)>> = BTreeMap::new();
    for row in rows.iter().filter(|r| r.get("status").map(String::as_str) == Some("ok")) {
        let value = if name == "distance" { metric(row, "distance_mean") } else { metric(row, name) };
        let seed = row.get("seed").and_then(|s| s.parse().ok()).unwrap_or(0);
        if let Some(v) = value {
            out.entry(cell_of(row)).or_default().push((seed, v));
        }
    }
    out.into_iter().map(|(k, v)| (k, Sample::seeded(v))).collect()
}

/// Writes `summary.csv`: per cell, runs, completions, and mean ± 95 % CI of each figure.
pub fn summarize(out: &Path) -> Result<(), ExperimentError> {
    let rows = read_runs(out)?;
    let figures = [
        "steps",
        "t50",
        "t90",
        "t95",
        "t100",
        "distance",
        "idle_steps",
        "overlap",
        "replans",
        "wall_time_s",
        "switches_per_100",
    ];
    let per_figure: Vec<BTreeMap<CellKey, Sample>> = figures.iter().map(|f| samples(&rows, f)).collect();
    let mut cells: BTreeMap<CellKey, (usize, usize, usize)> = BTreeMap::new();
    for row in &rows {
        let entry = cells.entry(cell_of(row)).or_default();
        entry.0 += 1;
        if row.get("completed").map(String::as_str) == Some("true") {
            entry.1 += 1;
        }
        if row.get("status").map(String::as_str) != Some("ok") {
            entry.2 += 1;
        }
    }
    let path = out.join("summary.csv");
    let mut writer = csv::Writer::from_path(&path).map_err(csv_error(&path))?;
    let mut header: Vec<String> =
        ["world", "label", "robots", "comm_range", "runs", "completed", "failed"].map(str::to_owned).to_vec();
    for f in figures {
        header.extend([format!("{f}_mean"), format!("{f}_ci95"), format!("{f}_n")]);
    }
    writer.write_record(&header).map_err(csv_error(&path))?;
    for (key, (runs, completed, failed)) in &cells {
        let mut row = vec![
            key.0.clone(),
            key.1.clone(),
            key.2.to_string(),
            key.3.clone(),
            runs.to_string(),
            completed.to_string(),
            failed.to_string(),
        ];
        for samples in &per_figure {
            match samples.get(key) {
                Some(s) => row.extend([format!("{:.4}", s.mean()), format!("{:.4}", s.ci95()), s.len().to_string()]),
                None => row.extend([String::new(), String::new(), "0".into()]),
            }
        }
        writer.write_record(&row).map_err(csv_error(&path))?;
    }
    writer.flush().map_err(io(&path))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn rows_with_commas_quotes_and_newlines_read_back_as_written() {
        let dir = tempfile::tempdir().unwrap();
        let mut file = RunsFile::open(dir.path()).unwrap();
        let mut row: Vec<String> = RUN_COLUMNS.iter().map(|c| format!("{c}-value")).collect();
        row[8] = "robot failed: \"no path\", twice\nthen stopped".to_owned();
        file.append(&row).unwrap();
        drop(file);
        // Reopening appends without a second header.
        RunsFile::open(dir.path()).unwrap().append(&row).unwrap();
        let rows = read_runs(dir.path()).unwrap();
        assert_eq!(rows.len(), 2);
        assert_eq!(rows[0]["error"], row[8]);
        assert_eq!(rows[1]["id"], "id-value");
    }
}
