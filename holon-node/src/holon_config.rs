//! Which kind of holon a config file describes (`kind`), and its config.

use std::path::Path;

use schemas::HolonId;

use holon::config_file::ConfigError;

use crate::config::ResourceConfig;
use crate::identity::Overrides;
use crate::product::ProductConfig;
use crate::staff::config::StaffConfig;

/// The config of whichever holon a file describes (its `kind`). A resource's, the
/// largest by far, is boxed.
#[derive(Debug, Clone)]
pub enum HolonConfig {
    Resource(Box<ResourceConfig>),
    Product(ProductConfig),
    Staff(StaffConfig),
}

impl HolonConfig {
    /// Reads `kind` (default `resource`) and loads the file as that kind of holon.
    ///
    /// The text is read as a table for its `kind`, then parsed again as that kind's
    /// file: only the second parse knows the fields, and its errors name the line.
    pub fn load(path: &Path, overrides: Overrides) -> Result<HolonConfig, ConfigError> {
        let (text, display) = holon::config_file::read(path)?;
        let table: toml::Table = holon::config_file::parse(&text, &display)?;
        match table
            .get("kind")
            .and_then(|k| k.as_str())
            .unwrap_or("resource")
        {
            "resource" => ResourceConfig::parse(&text, &display, overrides)
                .map(|c| HolonConfig::Resource(Box::new(c))),
            "product" => ProductConfig::parse(&text, &display, overrides).map(HolonConfig::Product),
            "staff" => StaffConfig::parse(&text, &display, overrides).map(HolonConfig::Staff),
            other => Err(ConfigError::Invalid {
                path: display,
                message: format!("kind: {other:?} is not resource, product or staff"),
            }),
        }
    }

    pub fn holon(&self) -> &HolonId {
        match self {
            HolonConfig::Resource(c) => &c.holon,
            HolonConfig::Product(c) => &c.identity.holon,
            HolonConfig::Staff(c) => &c.identity.holon,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::path::Path;

    #[test]
    fn every_demo_config_loads() {
        let dir = concat!(env!("CARGO_MANIFEST_DIR"), "/../deploy/cells/demo");
        let mut kinds = Vec::new();
        for file in [
            "robot1.toml",
            "inspect1.toml",
            "conveyor1.toml",
            "transfer1.toml",
            "breaker.toml",
        ] {
            let path = Path::new(dir).join(file);
            let config =
                HolonConfig::load(&path, Overrides::default()).unwrap_or_else(|e| panic!("{e}"));
            kinds.push(config.holon().to_string());
        }
        kinds.sort();
        assert!(
            kinds.contains(&"resource/conveyor1".to_string()),
            "{kinds:?}"
        );
        assert!(
            kinds.contains(&"resource/inspect1".to_string()),
            "{kinds:?}"
        );
        assert!(kinds.contains(&"product/breaker".to_string()), "{kinds:?}");
    }
}
