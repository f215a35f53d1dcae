//! The cell's namespace (`urn:holarchy:<cell>`): its nodes, their string NodeIds, and
//! the values a resource's state snapshot gives them.
//!
//! ```text
//! Objects/PackMLObjects/<resource>            PackMLObjects.<resource>
//!   Status/StateCurrent ... (Int32, Boolean)  PackMLObjects.<resource>.Status.StateCurrent
//!   Admin/ProdProcessedCount ...              PackMLObjects.<resource>.Admin.ProdProcessedCount
//!   Admin/StopReason/ID, Message, DateTime    PackMLObjects.<resource>.Admin.StopReason.ID
//!   Start() ... Reset(), SetUnitMode(Int32)   PackMLObjects.<resource>.Hold
//! Objects/Cell                                Cell
//!   OrdersRunning, OrdersDone, OrdersFailed   Cell.OrdersRunning
//!   SubmitWorkOrder(String, Int32, Int32[,    Cell.SubmitWorkOrder
//!                   String])
//!   Security/LoginsRefused, LoginsInCheck,    Cell.Security.LoginsRefused
//!            SessionsActivated, SessionsWaiting
//! ```

use opcua::types::{
    Argument, DataTypeId, DateTime, LocalizedText, NodeId, ObjectId, ObjectTypeId, QualifiedName,
    UAString, VariableTypeId, Variant,
};
use opcua_server::address_space::{AddressSpace, MethodBuilder, ObjectBuilder, VariableBuilder};
use schemas::{PackmlStatus, ResourceSnapshot};

/// The folder of the resources (OPC 30050's name).
pub const PACKML_OBJECTS: &str = "PackMLObjects";

/// The cell's object.
pub const CELL: &str = "Cell";

/// The PackML commands a resource object has as methods (no arguments), by their
/// OPC 30050 names.
pub const COMMAND_METHODS: [&str; 9] = [
    "Start",
    "Stop",
    "Hold",
    "Unhold",
    "Suspend",
    "Unsuspend",
    "Abort",
    "Clear",
    "Reset",
];

/// The unit-mode method of a resource object.
pub const SET_UNIT_MODE: &str = "SetUnitMode";

/// The cell's method for work orders.
pub const SUBMIT_WORK_ORDER: &str = "SubmitWorkOrder";

/// The cell's order figures.
pub const ORDER_FIGURES: [&str; 3] = ["OrdersRunning", "OrdersDone", "OrdersFailed"];

/// The OPC UA server's own object under the cell's: its doors' figures.
pub const SECURITY: &str = "Security";

/// The server's door figures (Int32): logins refused since the start (wrong password,
/// unknown user, locked out, busy, a token kind not accepted), logins waiting for their
/// password check or being checked, sessions activated, sessions created and waiting
/// for activation.
pub const SECURITY_FIGURES: [&str; 4] = [
    "LoginsRefused",
    "LoginsInCheck",
    "SessionsActivated",
    "SessionsWaiting",
];

/// The namespace URI of a cell.
pub fn namespace_uri(cell: &str) -> String {
    format!("urn:holarchy:{cell}")
}

/// A string NodeId in our namespace.
pub fn id(ns: u16, path: &str) -> NodeId {
    NodeId::new(ns, path.to_string())
}

/// The NodeId path of a resource's object.
pub fn resource_path(resource: &str) -> String {
    format!("{PACKML_OBJECTS}.{resource}")
}

/// What a method's NodeId names: a resource's method, or the cell's.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum MethodTarget {
    /// `PackMLObjects.<resource>.<method>`.
    Resource {
        /// The resource's name.
        resource: String,
        /// The method's browse name, e.g. `Hold`.
        method: String,
    },
    /// `Cell.<method>`.
    Cell {
        /// The method's browse name.
        method: String,
    },
}

/// Which method a NodeId's string names (`None`: not one of ours).
pub fn method_target(path: &str) -> Option<MethodTarget> {
    if let Some(method) = path.strip_prefix(&format!("{CELL}.")) {
        return Some(MethodTarget::Cell {
            method: method.to_string(),
        });
    }
    let rest = path.strip_prefix(&format!("{PACKML_OBJECTS}."))?;
    let (resource, method) = rest.rsplit_once('.')?;
    Some(MethodTarget::Resource {
        resource: resource.to_string(),
        method: method.to_string(),
    })
}

fn argument(name: &str, data_type: DataTypeId, array: bool, description: &str) -> Argument {
    Argument {
        name: UAString::from(name),
        data_type: data_type.into(),
        value_rank: if array { 1 } else { -1 },
        // An array argument needs its dimensions, or it cannot be encoded.
        array_dimensions: if array { Some(vec![0]) } else { None },
        description: LocalizedText::new("en", description),
    }
}

fn variable(space: &mut AddressSpace, ns: u16, parent: &str, name: &str, value: Variant) {
    let data_type = match &value {
        Variant::Int32(_) => DataTypeId::Int32,
        Variant::Boolean(_) => DataTypeId::Boolean,
        Variant::String(_) => DataTypeId::String,
        Variant::DateTime(_) => DataTypeId::DateTime,
        _ => DataTypeId::BaseDataType,
    };
    VariableBuilder::new(
        &id(ns, &format!("{parent}.{name}")),
        QualifiedName::new(ns, name),
        name,
    )
    .component_of(id(ns, parent))
    .has_type_definition(VariableTypeId::BaseDataVariableType)
    .data_type(data_type)
    .value(value)
    .insert(space);
}

fn object(space: &mut AddressSpace, ns: u16, parent: &str, name: &str) -> String {
    let path = format!("{parent}.{name}");
    ObjectBuilder::new(&id(ns, &path), QualifiedName::new(ns, name), name)
        .component_of(id(ns, parent))
        .has_type_definition(ObjectTypeId::BaseObjectType)
        .insert(space);
    path
}

fn method(
    space: &mut AddressSpace,
    ns: u16,
    parent: &str,
    name: &str,
    inputs: &[Argument],
    outputs: &[Argument],
) {
    let path = format!("{parent}.{name}");
    let mut builder = MethodBuilder::new(&id(ns, &path), QualifiedName::new(ns, name), name)
        .component_of(id(ns, parent))
        .executable(true)
        .user_executable(true);
    if !inputs.is_empty() {
        builder = builder.input_args(space, &id(ns, &format!("{path}.InputArguments")), inputs);
    }
    if !outputs.is_empty() {
        builder = builder.output_args(space, &id(ns, &format!("{path}.OutputArguments")), outputs);
    }
    builder.insert(space);
}

/// The nodes that are always there: the PackMLObjects folder and the cell's object.
pub fn add_static(space: &mut AddressSpace, ns: u16) {
    space.add_folder(
        &id(ns, PACKML_OBJECTS),
        QualifiedName::new(ns, PACKML_OBJECTS),
        PACKML_OBJECTS,
        &ObjectId::ObjectsFolder.into(),
    );
    ObjectBuilder::new(&id(ns, CELL), QualifiedName::new(ns, CELL), CELL)
        .organized_by(ObjectId::ObjectsFolder)
        .has_type_definition(ObjectTypeId::BaseObjectType)
        .insert(space);
    for figure in ORDER_FIGURES {
        variable(space, ns, CELL, figure, Variant::Int32(0));
    }
    let security = object(space, ns, CELL, SECURITY);
    for figure in SECURITY_FIGURES {
        variable(space, ns, &security, figure, Variant::Int32(0));
    }
    method(
        space,
        ns,
        CELL,
        SUBMIT_WORK_ORDER,
        &[
            argument(
                "product",
                DataTypeId::String,
                false,
                "the product, e.g. breaker",
            ),
            argument("count", DataTypeId::Int32, false, "how many, 1 to 10000"),
            argument(
                "priority",
                DataTypeId::Int32,
                false,
                "-1000 to 1000, higher first",
            ),
            argument(
                "submitId",
                DataTypeId::String,
                false,
                "optional: a name for the work order ('' or left out: none); called again under it, the orders made then, none made",
            ),
        ],
        &[argument(
            "orderIds",
            DataTypeId::String,
            true,
            "the new orders",
        )],
    );
}

/// Every node of a resource, children before their parents.
fn resource_nodes(resource: &str) -> Vec<String> {
    let root = resource_path(resource);
    let mut nodes = Vec::new();
    for name in [
        "StateCurrent",
        "UnitModeCurrent",
        "StateRequested",
        "StateChangeInProcess",
    ] {
        nodes.push(format!("{root}.Status.{name}"));
    }
    nodes.push(format!("{root}.Status"));
    for name in ["ID", "Message", "DateTime"] {
        nodes.push(format!("{root}.Admin.StopReason.{name}"));
    }
    nodes.push(format!("{root}.Admin.StopReason"));
    for name in ["ProdProcessedCount", "ProdDefectiveCount"] {
        nodes.push(format!("{root}.Admin.{name}"));
    }
    nodes.push(format!("{root}.Admin"));
    for name in COMMAND_METHODS {
        nodes.push(format!("{root}.{name}"));
    }
    nodes.push(format!("{root}.{SET_UNIT_MODE}.InputArguments"));
    nodes.push(format!("{root}.{SET_UNIT_MODE}"));
    nodes.push(root);
    nodes
}

/// Adds `Objects/PackMLObjects/<resource>` with its variables (at their initial values,
/// Undefined) and methods; false if it is there already.
pub fn add_resource(space: &mut AddressSpace, ns: u16, resource: &str) -> bool {
    let root = resource_path(resource);
    if space.node_exists(&id(ns, &root)) {
        return false;
    }
    ObjectBuilder::new(&id(ns, &root), QualifiedName::new(ns, resource), resource)
        .organized_by(id(ns, PACKML_OBJECTS))
        .has_type_definition(ObjectTypeId::BaseObjectType)
        .insert(space);
    let status = object(space, ns, &root, "Status");
    let admin = object(space, ns, &root, "Admin");
    let stop_reason = object(space, ns, &admin, "StopReason");
    for (path, value) in values(resource, None) {
        let (parent, name) = path.rsplit_once('.').expect("a child's path");
        debug_assert!(parent == status || parent == admin || parent == stop_reason);
        variable(space, ns, parent, name, value);
    }
    for name in COMMAND_METHODS {
        method(space, ns, &root, name, &[], &[]);
    }
    method(
        space,
        ns,
        &root,
        SET_UNIT_MODE,
        &[argument(
            "UnitMode",
            DataTypeId::Int32,
            false,
            "1 Production, 2 Maintenance, 3 Manual",
        )],
        &[],
    );
    true
}

/// Removes a resource's nodes (and the references to them); false if it was not there.
pub fn remove_resource(space: &mut AddressSpace, ns: u16, resource: &str) -> bool {
    let mut removed = false;
    for path in resource_nodes(resource) {
        removed |= space.delete(&id(ns, &path), true).is_some();
    }
    removed
}

fn int(value: u64) -> Variant {
    Variant::Int32(i32::try_from(value).unwrap_or(i32::MAX))
}

/// The values of a resource's variables (NodeId paths) from its PackML figures; a holon
/// without PackML (`None`) shows Undefined (0).
pub fn values(resource: &str, packml: Option<&PackmlStatus>) -> Vec<(String, Variant)> {
    let root = resource_path(resource);
    let status = format!("{root}.Status");
    let admin = format!("{root}.Admin");
    let reason = packml.and_then(|p| p.stop_reason.as_ref());
    vec![
        (
            format!("{status}.StateCurrent"),
            Variant::Int32(packml.map_or(0, |p| p.state_number)),
        ),
        (
            format!("{status}.UnitModeCurrent"),
            Variant::Int32(packml.map_or(0, |p| p.mode.number())),
        ),
        (
            format!("{status}.StateRequested"),
            Variant::Int32(packml.map_or(0, |p| p.state_requested.number())),
        ),
        (
            format!("{status}.StateChangeInProcess"),
            Variant::Boolean(packml.is_some_and(|p| p.state_requested != p.state)),
        ),
        (
            format!("{admin}.ProdProcessedCount"),
            int(packml.map_or(0, |p| p.processed)),
        ),
        (
            format!("{admin}.ProdDefectiveCount"),
            int(packml.map_or(0, |p| p.defective)),
        ),
        (
            format!("{admin}.StopReason.ID"),
            Variant::Int32(reason.map_or(0, |r| r.id)),
        ),
        (
            format!("{admin}.StopReason.Message"),
            Variant::String(UAString::from(
                reason.map_or(String::new(), |r| r.message.clone()),
            )),
        ),
        (
            format!("{admin}.StopReason.DateTime"),
            Variant::DateTime(Box::new(
                reason.map_or_else(DateTime::null, |r| DateTime::from(chrono_from_ms(r.at))),
            )),
        ),
    ]
}

/// A Unix time in ms as an OPC UA DateTime.
fn chrono_from_ms(ms: u64) -> opcua::types::DateTimeUtc {
    opcua::types::DateTimeUtc::from_timestamp_millis(i64::try_from(ms).unwrap_or(i64::MAX))
        .unwrap_or_default()
}

/// The values of a resource's snapshot.
pub fn snapshot_values(snapshot: &ResourceSnapshot) -> Vec<(String, Variant)> {
    values(snapshot.holon.name(), snapshot.packml.as_ref())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn method_node_ids_name_their_target() {
        assert_eq!(
            method_target("PackMLObjects.robot1.Hold"),
            Some(MethodTarget::Resource {
                resource: "robot1".into(),
                method: "Hold".into()
            })
        );
        assert_eq!(
            method_target("Cell.SubmitWorkOrder"),
            Some(MethodTarget::Cell {
                method: "SubmitWorkOrder".into()
            })
        );
        assert_eq!(method_target("robot1.Hold"), None);
    }
}
