//! `[layout]` in a resource holon's config: its own part of the cell's layout, checked
//! on its own (what it declares is consistent) when the config is loaded. What it names
//! of other holons (a dock on a conveyor, a transfer's far location) is checked where
//! the parts meet ([`super::CellLayout::assemble`]).

use std::collections::BTreeSet;

use serde::Deserialize;

use super::{
    ConveyorSpec, Dock, LayoutError, LayoutPart, LocationId, LocationRole, LocationSpec,
    TransferSpec, TransporterSpec, LAYOUT_VERSION,
};
use crate::validate_name;

/// `[layout]` as written.
#[derive(Debug, Clone, Default, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct LayoutSection {
    /// `[[layout.locations]]`: the places of this holon that hold parts.
    #[serde(default)]
    pub locations: Vec<LocationSection>,
    /// `[layout.conveyor]`: this holon is a palletised conveyor.
    #[serde(default)]
    pub conveyor: Option<ConveyorSection>,
    /// `[layout.transfer]`: this holon moves parts between two locations.
    #[serde(default)]
    pub transfer: Option<TransferSection>,
}

/// `[[layout.locations]]` as written.
#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct LocationSection {
    /// Its own name; its id is the holon's name, a dot and this (`robot1.port`).
    pub name: String,
    /// `port`, `input`, `output`, `buffer`, `entry`, `exit` or `entry_exit`.
    pub role: LocationRole,
    /// How many parts it holds at once (default 1).
    #[serde(default = "one")]
    pub capacity: i64,
    /// The conveyor stopper where it is reached (`conveyor1.s2`).
    #[serde(default)]
    pub dock: Option<String>,
}

fn one() -> i64 {
    1
}

/// `[layout.conveyor]` as written (the fields of [`ConveyorSpec`]).
pub type ConveyorSection = ConveyorSpec;

/// `[layout.transfer]` as written.
#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct TransferSection {
    /// The two locations it moves parts between (`robot1.port`), either way.
    pub between: Vec<String>,
    /// How long one move takes, in ms.
    pub move_ms: u64,
}

/// A resource config's holon name (`name_override`, else its `name`) and `[layout]`,
/// read from the config's text without the rest of its fields (`cell up --check`, the
/// plant simulator); None for another kind of holon, or a resource without `[layout]`.
pub fn from_resource_config(
    text: &str,
    name_override: Option<&str>,
) -> Result<Option<(String, LayoutSection)>, String> {
    let mut table: toml::Table = toml::from_str(text).map_err(|e| e.to_string())?;
    let kind = table
        .get("kind")
        .and_then(|k| k.as_str())
        .unwrap_or("resource");
    if kind != "resource" {
        return Ok(None);
    }
    let Some(layout) = table.remove("layout") else {
        return Ok(None);
    };
    let section: LayoutSection = layout.try_into().map_err(|e| format!("layout: {e}"))?;
    let name = match name_override {
        Some(name) => name.to_string(),
        None => table
            .get("name")
            .and_then(|n| n.as_str())
            .ok_or("name: missing")?
            .to_string(),
    };
    Ok(Some((name, section)))
}

/// The part of holon `holon` that a config's text states in its `[layout]` (tests and
/// tools that hold a config's text).
pub fn part_from_toml(holon: &str, text: &str) -> Result<LayoutPart, String> {
    let (_, section) = from_resource_config(text, Some(holon))?.ok_or("no [layout] in the text")?;
    section.part(holon).map_err(|e| e.to_string())
}

impl LayoutSection {
    /// Whether the holon takes no part in the layout (no `[layout]`).
    pub fn is_empty(&self) -> bool {
        self.locations.is_empty() && self.conveyor.is_none() && self.transfer.is_none()
    }

    /// The holon `holon`'s part of the layout, checked on its own: every error names
    /// the field.
    pub fn part(&self, holon: &str) -> Result<LayoutPart, LayoutError> {
        let mut locations = Vec::new();
        let mut names = BTreeSet::new();
        for (i, location) in self.locations.iter().enumerate() {
            let at = |field: &str| format!("layout.locations[{i}].{field}");
            let id = LocationId::new(holon, &location.name)
                .map_err(|e| LayoutError::new(at("name"), e))?;
            if !names.insert(location.name.as_str()) {
                return Err(LayoutError::new(
                    at("name"),
                    format!("{:?} is declared twice", location.name),
                ));
            }
            let capacity = u32::try_from(location.capacity)
                .ok()
                .filter(|c| *c >= 1)
                .ok_or_else(|| {
                    LayoutError::new(
                        at("capacity"),
                        format!(
                            "{} is below one: a location holds at least one part",
                            location.capacity
                        ),
                    )
                })?;
            let dock = location
                .dock
                .clone()
                .map(Dock::try_from)
                .transpose()
                .map_err(|e| LayoutError::new(at("dock"), e))?;
            locations.push(LocationSpec {
                id,
                role: location.role,
                capacity,
                dock,
            });
        }
        let has = |role: LocationRole| locations.iter().any(|l: &LocationSpec| l.role == role);
        match (has(LocationRole::Input), has(LocationRole::Output)) {
            (true, false) => {
                return Err(LayoutError::new(
                    "layout.locations",
                    "an input without an output: parts worked on here could never leave (or make it a port)",
                ))
            }
            (false, true) => {
                return Err(LayoutError::new(
                    "layout.locations",
                    "an output without an input: no part could arrive to be worked on (or make it a port)",
                ))
            }
            _ => {}
        }
        let transporter =
            match (&self.conveyor, &self.transfer) {
                (Some(_), Some(_)) => return Err(LayoutError::new(
                    "layout.transfer",
                    "a holon is one transporter: [layout.conveyor] or [layout.transfer], not both",
                )),
                (Some(conveyor), None) => {
                    check_conveyor(conveyor)?;
                    Some(TransporterSpec::Conveyor(conveyor.clone()))
                }
                (None, Some(transfer)) => Some(TransporterSpec::Transfer(transfer_spec(transfer)?)),
                (None, None) => None,
            };
        Ok(LayoutPart {
            v: LAYOUT_VERSION,
            holon: holon.to_string(),
            locations,
            transporter,
        })
    }
}

fn check_conveyor(conveyor: &ConveyorSpec) -> Result<(), LayoutError> {
    let field = |f: &str| format!("layout.conveyor.{f}");
    if conveyor.length_mm == 0 {
        return Err(LayoutError::new(
            field("length_mm"),
            "must be greater than 0",
        ));
    }
    if conveyor.speed_mm_s == 0 {
        return Err(LayoutError::new(
            field("speed_mm_s"),
            "must be greater than 0",
        ));
    }
    if conveyor.stoppers.is_empty() {
        return Err(LayoutError::new(
            field("stoppers"),
            "at least one stopper (where pallets stop and locations dock)",
        ));
    }
    let mut names = BTreeSet::new();
    let mut last_at = None;
    for (i, stopper) in conveyor.stoppers.iter().enumerate() {
        let at = |f: &str| field(&format!("stoppers[{i}].{f}"));
        validate_name("stopper name", &stopper.name)
            .map_err(|e| LayoutError::new(at("name"), e.to_string()))?;
        if !names.insert(stopper.name.as_str()) {
            return Err(LayoutError::new(
                at("name"),
                format!("{:?} is declared twice", stopper.name),
            ));
        }
        if stopper.at_mm >= conveyor.length_mm {
            return Err(LayoutError::new(
                at("at_mm"),
                format!(
                    "{} is not on the loop (length_mm {})",
                    stopper.at_mm, conveyor.length_mm
                ),
            ));
        }
        if last_at.is_some_and(|last| stopper.at_mm <= last) {
            return Err(LayoutError::new(
                at("at_mm"),
                "stoppers are listed in the order a pallet meets them: each further along than the one before",
            ));
        }
        last_at = Some(stopper.at_mm);
        if stopper.queue == 0 {
            return Err(LayoutError::new(
                at("queue"),
                "0 is below one: the track before a stopper holds at least one pallet",
            ));
        }
    }
    if conveyor.pallets == 0 {
        return Err(LayoutError::new(
            field("pallets"),
            "0 is below one: a conveyor moves parts on its pallets",
        ));
    }
    // One place on the tracks stays free, so that a pallet can always move on.
    if u64::from(conveyor.pallets) >= conveyor.track_capacity() {
        return Err(LayoutError::new(
            field("pallets"),
            format!(
                "{} pallets on tracks that hold {} (the stoppers' queues): at most {}, so that one place stays free and pallets can move",
                conveyor.pallets,
                conveyor.track_capacity(),
                conveyor.track_capacity().saturating_sub(1)
            ),
        ));
    }
    Ok(())
}

fn transfer_spec(transfer: &TransferSection) -> Result<TransferSpec, LayoutError> {
    let [a, b] = transfer.between.as_slice() else {
        return Err(LayoutError::new(
            "layout.transfer.between",
            format!(
                "{} locations: a transfer moves parts between two",
                transfer.between.len()
            ),
        ));
    };
    let id = |i: usize, id: &str| {
        LocationId::try_from(id.to_string())
            .map_err(|e| LayoutError::new(format!("layout.transfer.between[{i}]"), e))
    };
    let (a, b) = (id(0, a)?, id(1, b)?);
    if a == b {
        return Err(LayoutError::new(
            "layout.transfer.between",
            format!("{a} twice: a transfer moves parts between two locations"),
        ));
    }
    if transfer.move_ms == 0 {
        return Err(LayoutError::new(
            "layout.transfer.move_ms",
            "must be greater than 0",
        ));
    }
    Ok(TransferSpec {
        between: [a, b],
        move_ms: transfer.move_ms,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    fn section(toml_text: &str) -> LayoutSection {
        #[derive(Deserialize)]
        struct File {
            layout: LayoutSection,
        }
        let file: File = toml::from_str(toml_text).unwrap_or_else(|e| panic!("{e}"));
        file.layout
    }

    fn error(toml_text: &str) -> String {
        section(toml_text)
            .part("robot1")
            .expect_err("invalid")
            .to_string()
    }

    #[test]
    fn a_station_port_is_named_after_its_holon() {
        let part = section(
            "[[layout.locations]]\nname = \"port\"\nrole = \"port\"\ncapacity = 2\ndock = \"conveyor1.s2\"\n",
        )
        .part("robot2")
        .unwrap();
        assert_eq!(part.locations[0].id.as_str(), "robot2.port");
        assert_eq!(part.locations[0].capacity, 2);
        assert_eq!(
            part.locations[0].dock.as_ref().unwrap().to_string(),
            "conveyor1.s2"
        );
        let back = LayoutPart::from_json(&part.to_json()).unwrap();
        assert_eq!(back, part);
    }

    #[test]
    fn every_error_names_its_field() {
        let location = |extra: &str| {
            format!("[[layout.locations]]\nname = \"port\"\nrole = \"port\"\n{extra}\n")
        };
        assert_eq!(
            error(&location("capacity = 0")),
            "layout.locations[0].capacity: 0 is below one: a location holds at least one part"
        );
        assert!(error(&location("capacity = -3"))
            .starts_with("layout.locations[0].capacity: -3 is below one"));
        assert!(error(&location("dock = \"conveyor1\""))
            .starts_with("layout.locations[0].dock: \"conveyor1\": not CONVEYOR.STOPPER"));
        assert!(error(&format!("{}{}", location(""), location("")))
            .starts_with("layout.locations[1].name: \"port\" is declared twice"));
        let conveyor =
            |body: &str| format!("[layout.conveyor]\nlength_mm = 4000\nspeed_mm_s = 200\n{body}\n");
        assert!(error(&conveyor("pallets = 2\nstoppers = []"))
            .starts_with("layout.conveyor.stoppers: at least one stopper"));
        assert!(error(&conveyor(
            "pallets = 2\nstoppers = [{ name = \"a\", at_mm = 10 }, { name = \"b\", at_mm = 5 }]"
        ))
        .starts_with("layout.conveyor.stoppers[1].at_mm: stoppers are listed in the order"));
        assert!(error(&conveyor(
            "pallets = 2\nstoppers = [{ name = \"a\", at_mm = 4000 }]"
        ))
        .starts_with("layout.conveyor.stoppers[0].at_mm: 4000 is not on the loop"));
        assert!(error(&conveyor(
            "pallets = 4\nstoppers = [{ name = \"a\", at_mm = 0 }, { name = \"b\", at_mm = 5, queue = 2 }]"
        ))
        .starts_with("layout.conveyor.pallets: 4 pallets on tracks that hold 4"));
        assert!(
            error("[[layout.locations]]\nname = \"in\"\nrole = \"input\"\n")
                .starts_with("layout.locations: an input without an output")
        );
        assert!(
            error("[layout.transfer]\nbetween = [\"robot1.port\"]\nmove_ms = 10\n")
                .starts_with("layout.transfer.between: 1 locations")
        );
        assert!(error(
            "[layout.transfer]\nbetween = [\"robot1.port\", \"inspect1\"]\nmove_ms = 10\n"
        )
        .starts_with("layout.transfer.between[1]: location \"inspect1\": not HOLON.NAME"));
    }

    #[test]
    fn a_conveyor_times_its_moves_one_way_round() {
        let part = section(
            "[layout.conveyor]\nlength_mm = 4000\nspeed_mm_s = 200\npallets = 3\nstoppers = [{ name = \"load\", at_mm = 0 }, { name = \"s1\", at_mm = 1000 }, { name = \"s2\", at_mm = 3000 }]\n",
        )
        .part("conveyor1")
        .unwrap();
        let Some(TransporterSpec::Conveyor(conveyor)) = part.transporter else {
            panic!("a conveyor");
        };
        assert_eq!(conveyor.travel_ms("load", "s1"), Some(5_000));
        assert_eq!(conveyor.travel_ms("s2", "s1"), Some(10_000));
        assert_eq!(conveyor.travel_ms("s1", "s1"), Some(0));
        assert_eq!(conveyor.travel_ms("s1", "nowhere"), None);
    }
}
