//! The product holon: knows how its product is made and answers
//! `product/<product>/plan` with the process plan from its config.

use holon::life::{Behaviour, Leaving, LivelinessClaim, Next, StandInSpec, Start, Work};
use holon::ZenohSettings;
use schemas::{unix_ms, HolonKind, Plan, PlanStep};
use serde::Deserialize;
use tokio_util::sync::CancellationToken;
use tracing::{error, info, warn};

use holon::config_file::ConfigError;

use crate::identity::{Header, Identity, Overrides};
use crate::HolonError;

/// The product config file as written (`deploy/cells/demo/breaker.toml` documents it).
#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
struct ProductFile {
    /// Its cell.
    cell: String,
    /// Its name (`product/<name>`).
    name: String,
    /// `product`.
    kind: String,
    /// How it joins the cell.
    #[serde(default)]
    zenoh: ZenohSettings,
    /// Its parts are moved through the cell's layout (`Plan::moves_parts`).
    #[serde(default)]
    moves_parts: bool,
    /// How the product is made.
    steps: Vec<PlanStep>,
}

/// A validated product config.
#[derive(Debug, Clone)]
pub struct ProductConfig {
    /// Its cell, id (`product/<name>`) and zenoh settings.
    pub identity: Identity,
    /// The process plan it answers.
    pub plan: Plan,
}

impl ProductConfig {
    pub fn parse(
        text: &str,
        path: &str,
        overrides: Overrides,
    ) -> Result<ProductConfig, ConfigError> {
        let invalid = holon::config_file::invalid(path);
        let file: ProductFile = holon::config_file::parse(text, path)?;
        let header = Header {
            cell: file.cell,
            name: file.name,
            zenoh: file.zenoh,
        };
        let identity =
            Identity::from_header(header, &file.kind, HolonKind::Product, path, &overrides)?;
        let plan = Plan {
            product: identity.holon.name().to_string(),
            steps: file.steps,
            moves_parts: file.moves_parts,
        };
        plan.validate()
            .map_err(|e| invalid(format!("steps: {e}")))?;
        Ok(ProductConfig { identity, plan })
    }
}

/// Serves the plan until `shutdown` is cancelled, or until it hands over to a successor.
pub async fn run(config: ProductConfig, shutdown: CancellationToken) -> Result<(), HolonError> {
    let process = config.identity.process();
    holon::life::run(process, &config, LivelinessClaim::default(), shutdown).await
}

impl Behaviour for &ProductConfig {
    type Grant = ();
    type Work = Serving;
    type Error = HolonError;

    /// Answers the plan and the state on their keys, and publishes the state.
    async fn start(&mut self, start: Start<()>) -> Result<Serving, HolonError> {
        let config = *self;
        let session = start.session;
        let holon = config.identity.holon.clone();
        let zenoh_error = |e: zenoh::Error| HolonError::Zenoh(holon::zenoh_error::describe(&e));
        let plan = serde_json::to_vec(&config.plan).expect("a plan serializes");
        let snapshot = serde_json::json!({
            "holon": holon,
            "state": "serving",
            "version": crate::VERSION,
            "v": schemas::SERVICE_VERSION,
            "product": config.plan.product,
            "steps": config.plan.steps.len(),
            "at": unix_ms(),
        });
        let snapshot = serde_json::to_vec(&snapshot).expect("a snapshot serializes");
        let plan_key = config.identity.keys.plan(holon.name());
        let plan_queryable = session
            .declare_queryable(&plan_key)
            .callback({
                let holon = holon.clone();
                let plan_key = plan_key.clone();
                move |query| {
                    use zenoh::Wait;
                    info!(holon = %holon, message_type = "plan", "plan requested");
                    if let Err(e) = query.reply(&plan_key, plan.clone()).wait() {
                        error!(holon = %holon, error = %e, "cannot send the plan");
                    }
                }
            })
            .await
            .map_err(zenoh_error)?;
        let state_key = config.identity.keys.state(&holon);
        let state_queryable = session
            .declare_queryable(&state_key)
            .callback({
                let snapshot = snapshot.clone();
                let state_key = state_key.clone();
                let holon = holon.clone();
                move |query| {
                    use zenoh::Wait;
                    // Replied on the concrete key, whatever wildcard the query used.
                    if let Err(e) = query.reply(&state_key, snapshot.clone()).wait() {
                        warn!(holon = %holon, error = %e, "cannot reply with the state");
                    }
                }
            })
            .await
            .map_err(zenoh_error)?;
        session
            .put(&state_key, snapshot)
            .await
            .map_err(zenoh_error)?;
        info!(holon = %holon, key = %plan_key, steps = config.plan.steps.len(), "plan offered");
        Ok(Serving {
            stand_in: config.identity.stand_in(plan_key),
            holon,
            _plan: plan_queryable,
            _state: state_queryable,
        })
    }
}

/// A product serving its plan: its queryables, while it serves.
pub struct Serving {
    /// Its stand-in on the plan's key, for a hand-over.
    stand_in: holon::life::StandInSpec,
    /// `product/<name>`, for the log.
    holon: schemas::HolonId,
    /// Answers `product/<name>/plan`.
    _plan: zenoh::query::Queryable<()>,
    /// Answers `product/<name>/state`.
    _state: zenoh::query::Queryable<()>,
}

impl Work for Serving {
    type Event = std::convert::Infallible;
    type Error = HolonError;

    /// A product has no events of its own: its queryables answer by themselves.
    async fn next(&mut self) -> Next<Self::Event, HolonError> {
        std::future::pending().await
    }

    async fn handle(&mut self, event: Self::Event) {
        match event {}
    }

    fn stand_in(&self) -> StandInSpec {
        self.stand_in.clone()
    }

    /// Its queryables go (on a hand-over, after the stand-in is declared).
    async fn stop(self, _how: &Leaving) -> Result<(), HolonError> {
        info!(holon = %self.holon, "holon stopped");
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const DEMO: &str = include_str!("../../deploy/cells/demo/breaker.toml");

    #[test]
    fn the_demo_product_loads() {
        let config = ProductConfig::parse(DEMO, "breaker.toml", Overrides::default()).unwrap();
        assert_eq!(config.identity.holon.to_string(), "product/breaker");
        assert_eq!(config.plan.product, "breaker");
        let types: Vec<&str> = config
            .plan
            .steps
            .iter()
            .map(|s| s.service_type.as_str())
            .collect();
        // Its parts move: the plan names the work, the order books the moves.
        assert!(config.plan.moves_parts);
        assert_eq!(types, ["pick_n_place", "inspect"]);
        assert!(config.plan.steps[0].info.contains_key("pick"));
    }

    #[test]
    fn bad_plans_are_refused_when_loaded() {
        let cases = [
            ("from_step = 1", "from_step = 9", "from_step"),
            (
                "service_type = \"inspect\"",
                "service_type = \"Inspect\"",
                "service type",
            ),
            ("kind = \"product\"", "kind = \"products\"", "kind"),
        ];
        for (from, to, expect) in cases {
            assert!(DEMO.contains(from), "{from}");
            let err =
                ProductConfig::parse(&DEMO.replacen(from, to, 1), "b.toml", Overrides::default())
                    .unwrap_err()
                    .to_string();
            assert!(err.contains(expect), "{to}: {err}");
        }
    }
}
