//! A copy of a shipped cell for one run: its files in a directory of the run's own,
//! its manifest told to trace the plant, serve the plant's control port, and (for
//! contract net alone) start no staff holon.

use std::path::{Path, PathBuf};

use ::cell::up::manifest::Manifest;
use anyhow::{anyhow, Context, Result};

/// What the run needs to know of its copy of the cell.
#[derive(Debug, Clone)]
pub struct CellCopy {
    /// The copy's directory (`cell up` runs it).
    pub dir: PathBuf,
    /// The cell's name.
    pub cell: String,
    /// Its router's endpoint (`tcp/...`), where the bench connects.
    pub endpoint: String,
    /// The plant's control port.
    pub control: String,
    /// The plant's trace file.
    pub trace: PathBuf,
    /// The resource holons it starts (the manifest's holon-node processes whose
    /// config is a resource), the product holons and the staff holons.
    pub resources: Vec<String>,
    pub products: Vec<String>,
    pub staff: Vec<String>,
}

/// Files a cell's directory gets from running it (`cell up` by hand), which a run's
/// copy must not start from: the plant's state file (a plant resumes from the memory in
/// it) and its trace.
const RUNS_OWN_FILES: [&str; 3] = [
    "plant-state.json",
    "plant-state.json.next",
    "plant-trace.jsonl",
];

/// Copies the cell in `from` to `to` (its files, not its data, logs or run
/// directories) with its manifest rewritten: the plant traced and controlled at
/// `control`, and its staff holons left out unless `with_staff`.
pub fn copy(from: &Path, to: &Path, control: &str, with_staff: bool) -> Result<CellCopy> {
    std::fs::create_dir_all(to)?;
    for entry in std::fs::read_dir(from).with_context(|| format!("{}", from.display()))? {
        let entry = entry?;
        let runs_own = RUNS_OWN_FILES.iter().any(|f| entry.file_name() == *f);
        if entry.file_type()?.is_file() && !runs_own {
            std::fs::copy(entry.path(), to.join(entry.file_name()))?;
        }
    }
    // What the manifest says, read (and checked) as `cell up` reads it; the copy's
    // file is then rewritten as a plain table, so that everything else in it stays.
    let read = Manifest::load(to)?;
    let endpoint = read
        .router
        .as_ref()
        .and_then(|r| r.listen.first())
        .ok_or_else(|| anyhow!("{}: no [router] listen to connect to", to.display()))?
        .clone();
    let mut copy = CellCopy {
        dir: to.to_path_buf(),
        cell: read.cell.clone(),
        endpoint,
        control: control.to_string(),
        trace: to.join("plant-trace.jsonl"),
        resources: Vec::new(),
        products: Vec::new(),
        staff: Vec::new(),
    };
    let path = to.join("cell.toml");
    let mut manifest: toml::Table = toml::from_str(&std::fs::read_to_string(&path)?)
        .with_context(|| format!("{}", path.display()))?;
    let processes = manifest
        .get_mut("process")
        .and_then(|p| p.as_array_mut())
        .ok_or_else(|| anyhow!("{}: no [[process]]", path.display()))?;
    let mut kept = Vec::new();
    // The table's processes, in the manifest's order, beside what each says.
    for (mut process, section) in processes.drain(..).zip(&read.processes) {
        if section.program == "plant-sim" {
            let mut traced = section.args.clone();
            traced.extend(["--trace", "plant-trace.jsonl", "--control", control].map(String::from));
            if let Some(table) = process.as_table_mut() {
                table.insert("args".into(), toml::Value::from(traced));
            }
        } else if section.program == "holon-node" {
            let (name, kind) = holon_of(to, &section.args)?;
            match kind.as_str() {
                "staff" if !with_staff => continue,
                "staff" => copy.staff.push(name),
                "product" => copy.products.push(name),
                _ => copy.resources.push(name),
            }
        }
        kept.push(process);
    }
    *processes = kept;
    std::fs::write(&path, toml::to_string(&manifest)?)?;
    Ok(copy)
}

/// The name and kind of the holon a holon-node process runs (from its `--config`).
fn holon_of(dir: &Path, args: &[String]) -> Result<(String, String)> {
    let config = args
        .iter()
        .position(|a| a == "--config")
        .and_then(|i| args.get(i + 1))
        .ok_or_else(|| anyhow!("a holon-node process without --config: {args:?}"))?;
    let path = dir.join(config);
    let table: toml::Table = toml::from_str(&std::fs::read_to_string(&path)?)
        .with_context(|| format!("{}", path.display()))?;
    let field = |key: &str| {
        table
            .get(key)
            .and_then(|v| v.as_str())
            .map(str::to_string)
            .ok_or_else(|| anyhow!("{}: no {key}", path.display()))
    };
    Ok((field("name")?, field("kind")?))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_copy_leaves_a_run_by_hand_behind() {
        let shipped = holarchy_tests::workspace_root().join("deploy/cells/aip-primeca");
        let ran = tempfile::tempdir().unwrap();
        copy(&shipped, ran.path(), "127.0.0.1:9", false).unwrap();
        for file in RUNS_OWN_FILES {
            std::fs::write(ran.path().join(file), "{}").unwrap();
        }
        let dir = tempfile::tempdir().unwrap();
        copy(ran.path(), dir.path(), "127.0.0.1:9", false).unwrap();
        for file in RUNS_OWN_FILES {
            assert!(!dir.path().join(file).exists(), "{file} copied");
        }
        assert!(dir.path().join("monorail.toml").exists());
    }

    #[test]
    fn a_copy_without_staff_traces_its_plant_and_starts_no_staff_holon() {
        let from = holarchy_tests::workspace_root().join("deploy/cells/aip-primeca");
        let dir = tempfile::tempdir().unwrap();
        let copy = copy(&from, dir.path(), "127.0.0.1:9", false).unwrap();
        assert_eq!(copy.cell, "aip-primeca");
        assert_eq!(copy.endpoint, "tcp/127.0.0.1:7747");
        assert!(copy.staff.is_empty());
        assert_eq!(copy.products.len(), 7);
        assert!(copy.resources.iter().any(|r| r == "monorail"));
        let written = Manifest::load(dir.path()).unwrap();
        assert!(!written.processes.iter().any(|p| p.name == "planner"));
        let plant = written
            .processes
            .iter()
            .find(|p| p.program == "plant-sim")
            .unwrap();
        assert!(plant.args.ends_with(&[
            "--trace".to_string(),
            "plant-trace.jsonl".into(),
            "--control".into(),
            "127.0.0.1:9".into()
        ]));
        let with_staff = copy_with_staff(&from);
        assert_eq!(with_staff.staff, ["planner"]);
    }

    fn copy_with_staff(from: &Path) -> CellCopy {
        let dir = tempfile::tempdir().unwrap();
        copy(from, dir.path(), "127.0.0.1:9", true).unwrap()
    }
}
