//! `plant-sim`: the cell's plant, simulated once for all its controllers
//! (docs/material-flow.md, "The plant").
//!
//! One process serves every controller of the cell, each on its own address in its own
//! dialect, as `robot-sim` serves one; behind them is one physical state
//! ([`model::Plant`]): where every part and pallet is. A conveyor's move runs track by
//! track at the conveyor's speed, its pallet waiting where the way ahead is full (a
//! full port, a full or jammed track); a station told to work at an empty port fails
//! with a physical error. The model is pure; [`drive`] advances its time. Where
//! everything is can be read at any moment from the state file (`state_file`, JSON,
//! rewritten after every change). The layout is the cell's own: the `[layout]` of the
//! resource configs the plant file names.

pub mod control;
pub mod controller;
mod drive;
pub mod model;
mod resume;
pub mod trace;

use std::collections::BTreeMap;
use std::net::SocketAddr;
use std::path::{Path, PathBuf};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use schemas::layout::CellLayout;
use schemas::TimeScale;
use serde::Deserialize;
use tokio::sync::Notify;
use tokio_util::sync::CancellationToken;
use tracing::warn;

use crate::sim::physics::PhysicsHook;
use crate::sim::{SimConfig, Simulator};
use controller::{ControllerPhysics, OnChange};
use model::Plant;
use trace::Trace;

/// The plant file (`deploy/cells/demo/plant.toml` documents it), as written.
#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct PlantFile {
    /// The resource configs whose `[layout]` make the plant's layout (paths relative to
    /// the plant file).
    pub layout: Vec<PathBuf>,
    /// Where the plant writes where everything is, after every change (relative to the
    /// working directory); None: nowhere.
    #[serde(default)]
    pub state_file: Option<PathBuf>,
    /// Where the plant writes every action its controllers ran, a JSON line each as it
    /// ends, in plant time ([`trace`]; relative to the working directory); None:
    /// nowhere.
    #[serde(default)]
    pub trace_file: Option<PathBuf>,
    /// The controllers it serves.
    #[serde(rename = "controller")]
    pub controllers: Vec<ControllerSection>,
}

/// `[[controller]]`: one controller of the plant.
#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ControllerSection {
    /// The resource whose controller it is: where it works (its layout's ports) or what
    /// it moves (its conveyor or transfer).
    pub resource: String,
    /// Where it listens, HOST:PORT (port 0: a free one, printed).
    pub listen: String,
    /// The dialect it speaks (a shipped one's name, or a file relative to the plant
    /// file); default holarchy-xml.
    #[serde(default = "default_dialect")]
    pub dialect: String,
    /// How long an action takes, in ms, unless `action_ms` names it (a move takes its
    /// travel time).
    #[serde(default)]
    pub delay_ms: u64,
    /// How long particular actions take, in ms (`{ pick = 300 }`).
    #[serde(default)]
    pub action_ms: BTreeMap<String, u64>,
    /// Every Nth `inspect` is answered `inspect_fail`.
    #[serde(default)]
    pub inspect_fail_every: Option<u64>,
    /// The controller is fenced, with this session lease in ms (as `robot-sim --fenced
    /// --lease-ms`): one holder at a time claims it, and it answers the state of each
    /// step id (`STEP_STATUS`), so a resource holon restarted mid-move learns from it
    /// what became of the move. The dialect must fence.
    #[serde(default)]
    pub fenced_lease_ms: Option<u64>,
    /// How many actions the controller runs at once on one connection (as `robot-sim
    /// --actions-at-once`; default 1, at least 1): a conveyor's PLC moving several
    /// pallets at once, each move answered with its own reply, matched by id. More than
    /// 1 needs a dialect whose replies carry the command's id (`correlation = "id"`).
    #[serde(default = "one_action_at_once")]
    pub actions_at_once: usize,
}

fn default_dialect() -> String {
    "holarchy-xml".into()
}

fn one_action_at_once() -> usize {
    1
}

/// What keeps the plant from starting.
#[derive(Debug, thiserror::Error)]
pub enum PlantError {
    #[error("cannot read {path}: {why}")]
    Read { path: String, why: String },
    #[error("{path}: {why}")]
    Invalid { path: String, why: String },
    #[error("{path}: the layout has problems:\n  {}", problems.join("\n  "))]
    Layout { path: String, problems: Vec<String> },
    #[error("{path}: the plant's memory does not fit its layout (remove the file or start plant-sim with --fresh):\n  {}", problems.join("\n  "))]
    Memory { path: String, problems: Vec<String> },
    #[error("cannot listen on {address} for {resource}: {why}")]
    Listen {
        resource: String,
        address: String,
        why: String,
    },
}

/// The plant's time: ms of plant time since it first started (the model takes it as
/// an argument), running `scale` times as fast as the wall clock (`plant-sim
/// --time-scale`). A plant resumed after its death goes on from the plant time it had.
#[derive(Debug, Clone, Copy)]
pub struct Clock {
    /// When this process's plant started.
    started: Instant,
    /// The plant time it started at (0, or the time a resumed plant had).
    from_ms: u64,
    /// How many times faster than real time the plant runs.
    scale: TimeScale,
}

impl Clock {
    /// A clock from now, at `scale`.
    pub fn start(scale: TimeScale) -> Clock {
        Clock::resume(scale, 0)
    }

    /// A clock from now, at `scale`, going on from plant time `from_ms`.
    pub fn resume(scale: TimeScale, from_ms: u64) -> Clock {
        Clock {
            started: Instant::now(),
            from_ms,
            scale,
        }
    }

    /// Plant ms since the plant first started.
    pub fn now_ms(&self) -> u64 {
        let wall_us = self.started.elapsed().as_micros() as f64;
        self.from_ms + (wall_us * self.scale.factor() / 1000.0) as u64
    }

    /// The plant ms that pass in one wall ms (at least 1): the slack a controller
    /// allows between its own timing of an action and the plant's.
    pub fn one_wall_ms(&self) -> u64 {
        self.scale.factor().ceil() as u64
    }

    /// The wall time a plant duration takes.
    pub fn wall(&self, plant: Duration) -> Duration {
        self.scale.wall(plant)
    }

    /// The instant `ms` of plant time after the plant first started (now, for a time
    /// before this process's start).
    pub fn at(&self, ms: u64) -> Instant {
        self.started
            + self
                .scale
                .wall(Duration::from_millis(ms.saturating_sub(self.from_ms)))
    }
}

/// The plant, its controllers bound and ready to run.
pub struct PlantSim {
    /// Each controller's resource and its simulator.
    controllers: Vec<(String, Simulator)>,
    /// The plant they share.
    plant: Arc<Mutex<Plant>>,
    /// The plant's time.
    clock: Clock,
    /// Writes the state file.
    write: OnChange,
    /// Writes the state file and wakes the task that drives the plant's time.
    on_change: OnChange,
    /// Wakes the task that drives the plant's time.
    wake: Arc<Notify>,
    /// The control port, if asked for ([`control`]).
    control: Option<tokio::net::TcpListener>,
    /// The moves under way when the plant died, resumed: each ends in the plant.
    resumed: Vec<model::ResumedMove>,
    /// Where every ended action is written (a resumed move's end too).
    trace: Trace,
}

/// The plant's layout, from the plant file at `path`.
pub fn layout_of(path: &Path, file: &PlantFile) -> Result<CellLayout, PlantError> {
    let base = path.parent().unwrap_or(Path::new("."));
    let mut parts = Vec::new();
    for config in &file.layout {
        let config = base.join(config);
        let text = std::fs::read_to_string(&config).map_err(|e| PlantError::Read {
            path: config.display().to_string(),
            why: e.to_string(),
        })?;
        let invalid = |why: String| PlantError::Invalid {
            path: config.display().to_string(),
            why,
        };
        let (name, section) = schemas::layout::from_resource_config(&text, None)
            .map_err(invalid)?
            .ok_or_else(|| invalid("a resource config without [layout]".into()))?;
        parts.push(section.part(&name).map_err(|e| invalid(e.to_string()))?);
    }
    let layout = CellLayout::assemble(parts);
    if !layout.problems.is_empty() {
        return Err(PlantError::Layout {
            path: path.display().to_string(),
            problems: layout.problems.iter().map(|p| p.to_string()).collect(),
        });
    }
    Ok(layout)
}

/// Reads the plant file.
pub fn read(path: &Path) -> Result<PlantFile, PlantError> {
    let text = std::fs::read_to_string(path).map_err(|e| PlantError::Read {
        path: path.display().to_string(),
        why: e.to_string(),
    })?;
    let file: PlantFile = toml::from_str(&text).map_err(|e| PlantError::Invalid {
        path: path.display().to_string(),
        why: e.to_string(),
    })?;
    if file.controllers.is_empty() {
        return Err(PlantError::Invalid {
            path: path.display().to_string(),
            why: "controller: at least one".into(),
        });
    }
    Ok(file)
}

/// Where the plant writes, overriding its plant file's `state_file` and `trace_file`
/// (None: as the plant file says), and whether it resumes.
#[derive(Debug, Clone, Default)]
pub struct Outputs {
    /// Where everything is, rewritten after every change; the plant resumes from the
    /// memory in it when it is there ([`resume`]).
    pub state_file: Option<PathBuf>,
    /// Every action its controllers ran ([`trace`]).
    pub trace_file: Option<PathBuf>,
    /// Start an empty plant, forgetting the state file's memory.
    pub fresh: bool,
}

/// A plant file read and checked, ready to bind.
pub struct Prepared {
    /// Each controller's resource, address and simulator settings.
    controllers: Vec<(String, String, SimConfig)>,
    /// The plant they share.
    plant: Arc<Mutex<Plant>>,
    /// The plant's time.
    clock: Clock,
    /// Writes the state file.
    write: OnChange,
    /// Writes the state file and wakes the task that drives the plant's time.
    on_change: OnChange,
    /// Wakes the task that drives the plant's time.
    wake: Arc<Notify>,
    /// Each controller's fence as the memory had it (empty: a new plant).
    fences: BTreeMap<String, crate::sim::fence::FenceMemory>,
    /// Filled with each controller's counts once bound: the state file's writer reads
    /// their fences.
    bound: resume::Fences,
    /// Where every ended action is written.
    trace: Trace,
}

/// Reads and checks the plant file at `path` and everything it names (the layout, each
/// controller's dialect, the memory in its state file unless `files.fresh`), without
/// listening anywhere.
/// The plant runs at `scale`: each controller's action times (`delay_ms`,
/// `action_ms`) and every move's travel take 1/`scale` of their plant time.
pub fn prepare(path: &Path, files: Outputs, scale: TimeScale) -> Result<Prepared, PlantError> {
    let file = read(path)?;
    let Outputs {
        state_file,
        trace_file,
        fresh,
    } = files;
    let layout = layout_of(path, &file)?;
    let base = path.parent().unwrap_or(Path::new("."));
    let state_file = state_file.or(file.state_file.clone());
    let memory = match &state_file {
        Some(state) if !fresh => resume::read_memory(state)?,
        _ => None,
    };
    let resuming = memory.is_some();
    let (plant, fences) = match memory {
        Some(memory) => {
            let plant =
                Plant::resume(layout, memory.plant).map_err(|problems| PlantError::Memory {
                    path: state_file.clone().unwrap_or_default().display().to_string(),
                    problems,
                })?;
            (plant, memory.fences)
        }
        None => (Plant::new(layout), BTreeMap::new()),
    };
    let clock = Clock::resume(scale, plant.now_ms());
    let plant = Arc::new(Mutex::new(plant));
    let bound = resume::Fences::default();
    let write = resume::state_writer(state_file, bound.clone());
    let trace = match trace_file.or(file.trace_file.clone()) {
        Some(path) => {
            let opened = if resuming {
                Trace::append(&path)
            } else {
                Trace::create(&path)
            };
            opened.map_err(|e| PlantError::Read {
                path: path.display().to_string(),
                why: format!("cannot write the trace: {e}"),
            })?
        }
        None => Trace::none(),
    };
    let wake = Arc::new(Notify::new());
    let on_change: OnChange = {
        let (write, wake) = (write.clone(), wake.clone());
        Arc::new(move |plant: &Plant| {
            write(plant);
            wake.notify_one();
        })
    };
    let mut controllers = Vec::new();
    for (i, c) in file.controllers.iter().enumerate() {
        let invalid = |why: String| PlantError::Invalid {
            path: path.display().to_string(),
            why: format!("controller[{i}] ({}): {why}", c.resource),
        };
        schemas::validate_name("resource", &c.resource).map_err(|e| invalid(e.to_string()))?;
        if controllers.iter().any(|(r, _, _)| r == &c.resource) {
            return Err(invalid("a second controller for the same resource".into()));
        }
        let dialect = crate::dialect::Dialect::load(&c.dialect, Some(base))
            .map_err(|e| invalid(format!("dialect: {e}")))?;
        dialect
            .check_simulatable()
            .map_err(|e| invalid(format!("dialect: {e}")))?;
        if dialect.role == crate::dialect::Role::ControllerConnects {
            return Err(invalid(format!(
                "dialect: in {} the controller connects to the holon; the plant's controllers listen",
                dialect.name
            )));
        }
        if c.fenced_lease_ms == Some(0) {
            return Err(invalid("fenced_lease_ms: must be more than 0".into()));
        }
        if c.fenced_lease_ms.is_some() && !dialect.fencing_supported() {
            return Err(invalid(format!(
                "fenced_lease_ms: the dialect {} cannot fence (it has no [fence])",
                dialect.name
            )));
        }
        SimConfig::check_actions_at_once(c.actions_at_once, &dialect)
            .map_err(|e| invalid(e.to_string()))?;
        let physics = ControllerPhysics::new(
            plant.clone(),
            clock,
            &c.resource,
            on_change.clone(),
            trace.clone(),
        );
        let config = SimConfig {
            delay: clock.wall(Duration::from_millis(c.delay_ms)),
            action_delays: c
                .action_ms
                .iter()
                .map(|(action, ms)| (action.clone(), clock.wall(Duration::from_millis(*ms))))
                .collect(),
            inspect_fail_every: c.inspect_fail_every,
            dialect: Some(dialect),
            physics: Some(PhysicsHook(Arc::new(physics))),
            fence_lease: c.fenced_lease_ms.map(Duration::from_millis),
            actions_at_once: c.actions_at_once,
            ..SimConfig::default()
        };
        controllers.push((c.resource.clone(), c.listen.clone(), config));
    }
    Ok(Prepared {
        controllers,
        plant,
        clock,
        write,
        on_change,
        wake,
        fences,
        bound,
        trace,
    })
}

impl PlantSim {
    /// Reads the plant file at `path` (`files` overriding its own) and binds every
    /// controller, and the control port at `control` if given; the plant runs at
    /// `scale` ([`prepare`]).
    pub async fn bind(
        path: &Path,
        files: Outputs,
        control: Option<&str>,
        scale: TimeScale,
    ) -> Result<PlantSim, PlantError> {
        let Prepared {
            controllers: prepared,
            plant,
            clock,
            write,
            on_change,
            wake,
            fences,
            bound,
            trace,
        } = prepare(path, files, scale)?;
        let mut controllers = Vec::new();
        for (resource, listen, config) in prepared {
            let simulator =
                Simulator::bind(&listen, config)
                    .await
                    .map_err(|e| PlantError::Listen {
                        resource: resource.clone(),
                        address: listen.clone(),
                        why: e.to_string(),
                    })?;
            controllers.push((resource, simulator));
        }
        let control = match control {
            Some(address) => Some(tokio::net::TcpListener::bind(address).await.map_err(|e| {
                PlantError::Listen {
                    resource: "the control port".into(),
                    address: address.to_string(),
                    why: e.to_string(),
                }
            })?),
            None => None,
        };
        let counts: Vec<_> = controllers
            .iter()
            .map(|(resource, sim)| (resource.clone(), sim.stats()))
            .collect();
        let resumed = {
            let mut plant = plant.lock().unwrap_or_else(|e| e.into_inner());
            let resumed = resume::resume_controllers(&mut plant, &counts, fences);
            if bound.set(counts).is_err() {
                unreachable!("the controllers are bound once");
            }
            // Where everything is from the start: nothing yet and every pallet free, or
            // as the memory had it.
            on_change(&plant);
            resumed
        };
        Ok(PlantSim {
            controllers,
            plant,
            clock,
            write,
            on_change,
            wake,
            control,
            resumed,
            trace,
        })
    }

    /// Each controller's resource and the address it listens on.
    pub fn addresses(&self) -> Vec<(String, SocketAddr)> {
        self.controllers
            .iter()
            .filter_map(|(resource, sim)| Some((resource.clone(), sim.local_addr().ok()?)))
            .collect()
    }

    /// Where everything is now.
    pub fn view(&self) -> model::PlantView {
        let mut plant = self.plant.lock().unwrap_or_else(|e| e.into_inner());
        controller::log_happenings(&plant.advance(self.clock.now_ms()));
        plant.view()
    }

    /// Where the control port listens, if it does.
    pub fn control_address(&self) -> Option<SocketAddr> {
        self.control.as_ref().and_then(|l| l.local_addr().ok())
    }

    /// Serves every controller, and the control port, and drives the plant's time,
    /// until `shutdown`.
    pub async fn run(self, shutdown: CancellationToken) {
        for resumed in self.resumed {
            let Some(stats) = self
                .controllers
                .iter()
                .find(|(resource, _)| *resource == resumed.transporter)
                .map(|(_, sim)| sim.stats())
            else {
                warn!(part = %resumed.part, transporter = %resumed.transporter, "a move under way when the plant died has no controller now: it goes on in the plant, untraced");
                continue;
            };
            tokio::spawn(resume::end_resumed_move(
                resumed,
                self.plant.clone(),
                self.clock,
                stats,
                self.trace.clone(),
                self.on_change.clone(),
                shutdown.clone(),
            ));
        }
        tokio::spawn(drive::drive(
            self.plant.clone(),
            self.clock,
            self.write.clone(),
            self.wake.clone(),
            shutdown.clone(),
        ));
        if let Some(listener) = self.control {
            let controllers = self
                .controllers
                .iter()
                .map(|(resource, sim)| (resource.clone(), sim.stats()))
                .collect();
            tokio::spawn(control::serve(
                listener,
                self.plant.clone(),
                self.clock,
                controllers,
                self.on_change.clone(),
                shutdown.clone(),
            ));
        }
        let running: Vec<_> = self
            .controllers
            .into_iter()
            .map(|(_, sim)| tokio::spawn(sim.run(shutdown.clone())))
            .collect();
        for controller in running {
            if let Err(e) = controller.await {
                warn!(error = %e, "a controller of the plant ended abnormally");
            }
        }
    }
}
