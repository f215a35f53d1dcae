//! The services a resource offers and the steps each one takes, from its config.

use std::collections::BTreeMap;
use std::time::Duration;

use schemas::Pose;
use serde_json::{Map, Value};

/// One step of a service: send `action` to the controller, wait for one of `until`.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Step {
    /// The controller action, e.g. `pick`.
    pub action: String,
    /// The results that complete the step, e.g. `picking_done`.
    pub until: Vec<String>,
    /// The key in the Service `info` whose pose goes with the command (`POS`), if any.
    pub position: Option<String>,
}

/// A service type: its steps and how long it usually takes (for proposals).
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct ServiceDefinition {
    pub steps: Vec<Step>,
    pub nominal_duration: Duration,
}

/// A job's `info` as its steps use it: read once, when the job is booked (or when its
/// `start` brings an `info` of its own), and carried with the booking and the job, so
/// neither the start nor each step reads the JSON again.
#[derive(Debug, Clone, PartialEq, Default)]
pub struct Parameters {
    /// The pose each step sends with its command (`POS`), in step order.
    pub poses: Vec<Option<Pose>>,
    /// The job's program (product variant), if `info` names one ([`PROGRAM_KEY`]).
    pub program: Option<String>,
    /// The `info` entries that are strings, numbers or booleans: each command carries
    /// them for a dialect's `{info.KEY}` placeholders.
    pub scalars: BTreeMap<String, Value>,
}

/// Every service type a resource offers.
#[derive(Debug, Clone, Default, PartialEq, Eq)]
pub struct ServiceCatalog {
    services: BTreeMap<String, ServiceDefinition>,
}

impl ServiceCatalog {
    pub fn new(services: BTreeMap<String, ServiceDefinition>) -> Self {
        ServiceCatalog { services }
    }

    /// Every service type's definition.
    pub fn definitions(&self) -> &BTreeMap<String, ServiceDefinition> {
        &self.services
    }

    pub fn get(&self, service_type: &str) -> Option<&ServiceDefinition> {
        self.services.get(service_type)
    }

    pub fn offers(&self, service_type: &str) -> bool {
        self.services.contains_key(service_type)
    }

    pub fn service_types(&self) -> impl Iterator<Item = &str> {
        self.services.keys().map(String::as_str)
    }

    /// Whether `info` holds what a job of `service_type` needs to run: every step's
    /// pose, and a valid `program` if it names one. The error says what is wrong.
    pub fn check(&self, service_type: &str, info: &Map<String, Value>) -> Result<(), String> {
        self.parameters(service_type, info).map(|_| ())
    }

    /// What a job of `service_type` takes from `info` (see [`Parameters`]), or what is
    /// wrong with it (as [`check`](Self::check) says).
    pub fn parameters(
        &self,
        service_type: &str,
        info: &Map<String, Value>,
    ) -> Result<Parameters, String> {
        let poses = self.poses(service_type, info)?;
        let program = program(info)?;
        let scalars = info
            .iter()
            .filter(|(_, v)| v.is_string() || v.is_number() || v.is_boolean())
            .map(|(k, v)| (k.clone(), v.clone()))
            .collect();
        Ok(Parameters {
            poses,
            program,
            scalars,
        })
    }

    /// The pose each step needs, from `info`; an error names what is missing or wrong.
    pub fn poses(
        &self,
        service_type: &str,
        info: &Map<String, Value>,
    ) -> Result<Vec<Option<Pose>>, String> {
        let definition = self
            .get(service_type)
            .ok_or_else(|| format!("service type {service_type:?} is not offered"))?;
        definition
            .steps
            .iter()
            .map(|step| {
                let Some(key) = &step.position else {
                    return Ok(None);
                };
                let value = info
                    .get(key)
                    .ok_or_else(|| format!("info.{key} (a pose for {}) is missing", step.action))?;
                let pose: Pose = serde_json::from_value(value.clone())
                    .map_err(|e| format!("info.{key} is not a pose {{x,y,z[,a,b,c]}}: {e}"))?;
                if !pose.is_finite() {
                    return Err(format!("info.{key} has a coordinate that is not finite"));
                }
                Ok(Some(pose))
            })
            .collect()
    }
}

/// The key of a job's `info` naming its program (product variant): each controller
/// command carries it (`PROGRAM`), and a controller changes over when it differs from
/// the last one it ran.
pub const PROGRAM_KEY: &str = "program";

/// The longest program name sent to a controller.
pub const MAX_PROGRAM_LEN: usize = 64;

/// The job's program from `info` ([`PROGRAM_KEY`]), if it names one: a non-empty
/// string of at most [`MAX_PROGRAM_LEN`] letters, digits, `_`, `-` or `.`.
pub fn program(info: &Map<String, Value>) -> Result<Option<String>, String> {
    let Some(value) = info.get(PROGRAM_KEY) else {
        return Ok(None);
    };
    let valid = value.as_str().filter(|p| {
        !p.is_empty()
            && p.len() <= MAX_PROGRAM_LEN
            && p.chars()
                .all(|c| c.is_ascii_alphanumeric() || matches!(c, '_' | '-' | '.'))
    });
    match valid {
        Some(p) => Ok(Some(p.to_string())),
        None => Err(format!(
            "info.{PROGRAM_KEY} must be 1 to {MAX_PROGRAM_LEN} letters, digits, _ - or ., not {value}"
        )),
    }
}

#[cfg(test)]
pub(crate) fn pick_n_place() -> ServiceCatalog {
    let step = |action: &str, until: &str, position: &str| Step {
        action: action.into(),
        until: vec![until.into()],
        position: Some(position.into()),
    };
    let mut services = BTreeMap::new();
    services.insert(
        "pick_n_place".to_string(),
        ServiceDefinition {
            steps: vec![
                step("pick", "picking_done", "pick"),
                step("place", "placing_done", "place"),
            ],
            nominal_duration: Duration::from_millis(1000),
        },
    );
    services.insert(
        "inspect".to_string(),
        ServiceDefinition {
            steps: vec![Step {
                action: "inspect".into(),
                until: vec!["inspect_pass".into(), "inspect_fail".into()],
                position: None,
            }],
            nominal_duration: Duration::from_millis(500),
        },
    );
    ServiceCatalog::new(services)
}

#[cfg(test)]
mod tests {
    use super::*;
    use serde_json::json;

    fn info(v: Value) -> Map<String, Value> {
        v.as_object().unwrap().clone()
    }

    #[test]
    fn a_job_may_name_its_program() {
        let poses = json!({"pick": {"x": 1, "y": 2, "z": 3}, "place": {"x": 4, "y": 5, "z": 6}});
        let catalog = pick_n_place();
        let mut with = info(poses.clone());
        assert_eq!(program(&with), Ok(None));
        with.insert(PROGRAM_KEY.into(), json!("breaker-b2.1"));
        assert_eq!(program(&with), Ok(Some("breaker-b2.1".into())));
        catalog.check("pick_n_place", &with).unwrap();
        for bad in [
            json!(""),
            json!(7),
            json!("a b"),
            json!("x".repeat(65)),
            json!("<P>"),
        ] {
            let mut info = info(poses.clone());
            info.insert(PROGRAM_KEY.into(), bad.clone());
            let why = catalog.check("pick_n_place", &info).unwrap_err();
            assert!(why.contains("info.program"), "{bad}: {why}");
        }
    }

    #[test]
    fn a_jobs_parameters_are_read_from_info_once() {
        let catalog = pick_n_place();
        let info = info(json!({
            "pick": {"x": 1, "y": 2, "z": 3},
            "place": {"x": 4, "y": 5, "z": 6},
            "program": "b2",
            "lot": "L7",
            "count": 3,
            "rework": false,
            "notes": ["not", "a", "scalar"]
        }));
        let parameters = catalog.parameters("pick_n_place", &info).unwrap();
        assert_eq!(parameters.poses.len(), 2);
        assert_eq!(parameters.poses[0].unwrap().x, 1.0);
        assert_eq!(parameters.program.as_deref(), Some("b2"));
        let scalars: Vec<&str> = parameters.scalars.keys().map(String::as_str).collect();
        assert_eq!(scalars, ["count", "lot", "program", "rework"]);
        assert_eq!(
            catalog.parameters("pick_n_place", &Map::new()).unwrap_err(),
            catalog.check("pick_n_place", &Map::new()).unwrap_err()
        );
    }

    #[test]
    fn extracts_the_poses_of_each_step() {
        let catalog = pick_n_place();
        let poses = catalog
            .poses(
                "pick_n_place",
                &info(json!({"pick": {"x": 1, "y": 2, "z": 3}, "place": {"x": 4, "y": 5, "z": 6, "c": 90}})),
            )
            .unwrap();
        assert_eq!(poses.len(), 2);
        assert_eq!(poses[1].unwrap().c, 90.0);
        assert_eq!(catalog.poses("inspect", &Map::new()).unwrap(), vec![None]);
    }

    #[test]
    fn says_what_is_wrong_with_info() {
        let catalog = pick_n_place();
        let err = catalog
            .poses(
                "pick_n_place",
                &info(json!({"pick": {"x": 1, "y": 2, "z": 3}})),
            )
            .unwrap_err();
        assert!(err.contains("info.place"), "{err}");
        let err = catalog
            .poses(
                "pick_n_place",
                &info(json!({"pick": {"x": "a"}, "place": {}})),
            )
            .unwrap_err();
        assert!(err.contains("info.pick"), "{err}");
        assert!(catalog.poses("weld", &Map::new()).is_err());
    }
}
