//! One fixture for "a resource with its simulator, ready".

use std::fs;
use std::path::PathBuf;

use anyhow::{Context, Result};

use crate::*;

/// How to start a [`Resource`] (from [`Cell::resource`]): the simulator's flags, the
/// controller's command timeout (5 s unless set), lines appended to the config written
/// by [`resource_config`], and the holon-node's extra flags.
pub struct ResourceBuilder<'a> {
    pub(crate) cell: &'a Cell,
    pub(crate) dir: PathBuf,
    pub(crate) name: String,
    pub(crate) sim_flags: Vec<String>,
    pub(crate) command_timeout_ms: u64,
    /// The first pause before reconnecting to the controller (`None`: the tests' 100 ms).
    pub(crate) reconnect_interval_ms: Option<u64>,
    pub(crate) config_extra: String,
    pub(crate) node_flags: Vec<String>,
    /// The controller dialect of both the simulator and the holon (None: the default).
    pub(crate) dialect: Option<String>,
}

impl ResourceBuilder<'_> {
    /// Flags of `robot-sim` (e.g. `--delay-ms 100`).
    pub fn sim_flags(mut self, flags: &[&str]) -> Self {
        self.sim_flags = flags.iter().map(|f| f.to_string()).collect();
        self
    }

    pub fn command_timeout_ms(mut self, timeout: u64) -> Self {
        self.command_timeout_ms = timeout;
        self
    }

    /// The first pause before the holon reconnects to its controller
    /// (`controller.reconnect_interval_ms`): a test that needs something to happen
    /// while the controller is away makes it long.
    pub fn reconnect_interval_ms(mut self, pause: u64) -> Self {
        self.reconnect_interval_ms = Some(pause);
        self
    }

    /// TOML appended to the resource's config (e.g. an `[agenda]` table).
    pub fn config(mut self, extra: &str) -> Self {
        self.config_extra.push_str(extra);
        self
    }

    /// The controller dialect both the simulator and the holon speak (a shipped name or
    /// a file), set in the config's `[controller]` section and by `--dialect`.
    pub fn dialect(mut self, dialect: &str) -> Self {
        self.dialect = Some(dialect.to_string());
        self
    }

    /// Extra flags of `holon-node` (e.g. `--data-dir DIR`).
    pub fn node_flags(mut self, flags: &[&str]) -> Self {
        self.node_flags = flags.iter().map(|f| f.to_string()).collect();
        self
    }

    /// Starts the simulator (`<name>-sim`), writes the config (`<name>.toml`) and starts
    /// the resource holon on it, and waits until the holon is alive and free.
    pub async fn start(self) -> Result<Resource> {
        let mut sim_flags: Vec<&str> = self.sim_flags.iter().map(String::as_str).collect();
        if let Some(dialect) = &self.dialect {
            sim_flags.extend(["--dialect", dialect.as_str()]);
        }
        let sim = Sim::start(
            &self.dir,
            &format!("{}-sim", self.name),
            "127.0.0.1:0",
            &sim_flags,
        )?;
        let config = resource_config(&self.dir, &self.name, self.command_timeout_ms)?;
        if let Some(pause) = self.reconnect_interval_ms {
            let text = fs::read_to_string(&config)?;
            let changed = text.replacen(
                "reconnect_interval_ms = 100\n",
                &format!("reconnect_interval_ms = {pause}\n"),
                1,
            );
            anyhow::ensure!(
                changed != text || pause == 100,
                "no reconnect_interval_ms to set"
            );
            fs::write(&config, changed)?;
        }
        if let Some(dialect) = &self.dialect {
            let text = fs::read_to_string(&config)?.replacen(
                "[controller]\n",
                &format!("[controller]\ndialect = {dialect:?}\n"),
                1,
            );
            fs::write(&config, text)?;
        }
        if !self.config_extra.is_empty() {
            let mut text = fs::read_to_string(&config)?;
            text.push_str(&self.config_extra);
            fs::write(&config, text)?;
        }
        let node_flags: Vec<&str> = self.node_flags.iter().map(String::as_str).collect();
        let node = self
            .cell
            .start_free_resource(&self.dir, &config, &sim.address, &node_flags)
            .await
            .with_context(|| format!("resource {} on its simulator", self.name))?;
        Ok(Resource { sim, node, config })
    }
}

/// A resource with its simulator, ready: the holon is alive and free. Both processes
/// are killed when it is dropped.
pub struct Resource {
    pub node: Process,
    pub sim: Sim,
    /// The resource's config, to start it (or a successor) again.
    pub config: PathBuf,
}
