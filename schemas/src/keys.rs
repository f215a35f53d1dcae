//! The key space of a cell: every zenoh key expression holarchy uses is built here.

use crate::id::{validate_name, HolonId, HolonKind};
use crate::SchemaError;

/// The root of every holarchy key.
pub const ROOT: &str = "holarchy";

/// The longest key expression we accept in a message (`reply_to`).
pub const MAX_KEY_LEN: usize = 512;

/// Checks that `key` is a concrete zenoh key expression (no wildcards, no empty chunk,
/// no leading or trailing `/`) under `holarchy/`, as `reply_to` must be.
pub fn validate_reply_key(key: &str) -> Result<(), SchemaError> {
    let invalid = |why: &str| SchemaError::InvalidKeyExpr {
        key: key.to_string(),
        why: why.to_string(),
    };
    if key.len() > MAX_KEY_LEN {
        return Err(invalid("it is longer than 512 bytes"));
    }
    if !key.starts_with("holarchy/") {
        return Err(invalid("it must start with holarchy/"));
    }
    for chunk in key.split('/') {
        if chunk.is_empty() {
            return Err(invalid("it has an empty chunk"));
        }
        if chunk.contains(['*', '$', '?', '#']) {
            return Err(invalid(
                "wildcards and the characters $ ? # are not allowed",
            ));
        }
        if chunk.chars().any(|c| c.is_control() || c.is_whitespace()) {
            return Err(invalid("control and whitespace characters are not allowed"));
        }
    }
    Ok(())
}

/// Builds the keys of one cell (`holarchy/<cell>/...`).
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct CellKeys {
    cell: String,
}

impl CellKeys {
    pub fn new(cell: &str) -> Result<Self, SchemaError> {
        validate_name("cell name", cell)?;
        Ok(CellKeys {
            cell: cell.to_string(),
        })
    }

    pub fn cell(&self) -> &str {
        &self.cell
    }

    fn prefix(&self) -> String {
        format!("{ROOT}/{}", self.cell)
    }

    /// `holarchy/<cell>/alive/<kind>/<name>`: the holon's liveliness token.
    pub fn alive(&self, holon: &HolonId) -> String {
        format!("{}/alive/{holon}", self.prefix())
    }

    /// `holarchy/<cell>/alive/**`: every holon of the cell.
    pub fn alive_all(&self) -> String {
        format!("{}/alive/**", self.prefix())
    }

    /// `holarchy/<cell>/alive/<kind>/*`: every holon of one kind.
    pub fn alive_kind(&self, kind: HolonKind) -> String {
        format!("{}/alive/{kind}/*", self.prefix())
    }

    /// Recovers the holon id from a liveliness key of this cell.
    pub fn holon_from_alive(&self, key: &str) -> Option<HolonId> {
        let rest = key.strip_prefix(&format!("{}/alive/", self.prefix()))?;
        rest.parse().ok()
    }

    /// `holarchy/<cell>/resource/<name>/service`: Service requests to one resource.
    pub fn service(&self, resource: &str) -> String {
        format!("{}/resource/{resource}/service", self.prefix())
    }

    /// `holarchy/<cell>/resource/<name>/outcome`: what became of a conversation (an
    /// [`crate::outcome::OutcomeRequest`] in, an [`crate::outcome::OutcomeReply`] out),
    /// asked by the order that booked it.
    pub fn outcome(&self, resource: &str) -> String {
        format!("{}/resource/{resource}/outcome", self.prefix())
    }

    /// `holarchy/<cell>/resource/<name>/packml`: PackML commands and unit mode changes
    /// to one resource (a [`crate::packml::PackmlRequest`] in, a
    /// [`crate::packml::PackmlReply`] out); operators only in a secure cell.
    pub fn packml(&self, resource: &str) -> String {
        format!("{}/resource/{resource}/packml", self.prefix())
    }

    /// `holarchy/<cell>/resource/<name>/carriers`: an operator's word on a conveyor's
    /// carriers, one taken out of service or put back (a [`crate::carrier::CarrierWord`]
    /// in, a [`crate::carrier::CarrierReply`] out); operators only in a secure cell.
    pub fn carriers(&self, resource: &str) -> String {
        format!("{}/resource/{resource}/carriers", self.prefix())
    }

    /// `holarchy/<cell>/offer/<service_type>/<name>`: one resource's offer of a service type.
    pub fn offer(&self, service_type: &str, resource: &str) -> String {
        format!("{}/offer/{service_type}/{resource}", self.prefix())
    }

    /// `holarchy/<cell>/offer/<service_type>/*`: all offers of a service type (contract net).
    pub fn offers(&self, service_type: &str) -> String {
        format!("{}/offer/{service_type}/*", self.prefix())
    }

    /// `holarchy/<cell>/resource/<name>/layout`: the resource's part of the cell's
    /// layout (`schemas::layout::LayoutPart`), answered while it serves.
    pub fn layout(&self, resource: &str) -> String {
        format!("{}/resource/{resource}/layout", self.prefix())
    }

    /// `holarchy/<cell>/resource/*/layout`: every serving resource's part of the layout.
    pub fn layout_all(&self) -> String {
        format!("{}/resource/*/layout", self.prefix())
    }

    /// `holarchy/<cell>/product/<product>/plan`.
    pub fn plan(&self, product: &str) -> String {
        format!("{}/product/{product}/plan", self.prefix())
    }

    /// `holarchy/<cell>/order/<name>/inbox`: where `done` / `failed` reach an order.
    pub fn inbox(&self, order: &str) -> String {
        format!("{}/order/{order}/inbox", self.prefix())
    }

    /// `holarchy/<cell>/order/<name>/cancel`: an operator cancels an order.
    pub fn cancel(&self, order: &str) -> String {
        format!("{}/order/{order}/cancel", self.prefix())
    }

    /// `holarchy/<cell>/order/<name>/part`: an operator says where the order's lost part
    /// is ([`crate::PartWord`]).
    pub fn part(&self, order: &str) -> String {
        format!("{}/order/{order}/part", self.prefix())
    }

    /// `holarchy/<cell>/order/<node>-$*/<leaf>`: `leaf` (`inbox`, `state`, `cancel`, `part`) of
    /// every order an order-node hosts (its orders are named `<node>-<n>`). The node
    /// declares its queryables on these, so it never answers for another node's orders
    /// and access control can grant each node its own orders' keys.
    pub fn node_orders(&self, node: &str, leaf: &str) -> String {
        format!("{}/order/{node}-$*/{leaf}", self.prefix())
    }

    /// `holarchy/<cell>/orders/submit`.
    pub fn orders_submit(&self) -> String {
        format!("{}/orders/submit", self.prefix())
    }

    /// `holarchy/<cell>/staff/<name>/advice`: a staff holon's advice to orders.
    pub fn advice(&self, staff: &str) -> String {
        format!("{}/staff/{staff}/advice", self.prefix())
    }

    /// `holarchy/<cell>/<kind>/<name>/state`: the holon's state snapshots.
    pub fn state(&self, holon: &HolonId) -> String {
        format!("{}/{}/{}/state", self.prefix(), holon.kind(), holon.name())
    }

    /// `holarchy/<cell>/resource/<name>/fence`: under it, each process of a fenced
    /// resource reports its place at the controller (`<prefix>/<zid>`).
    pub fn fence(&self, resource: &str) -> String {
        format!("{}/resource/{resource}/fence", self.prefix())
    }

    /// `holarchy/<cell>/resource/*/fence/*`: every fenced resource's processes.
    pub fn fence_all(&self) -> String {
        format!("{}/resource/*/fence/*", self.prefix())
    }

    /// `holarchy/<cell>/host/order-node/<name>/fence`: under it, each process of an
    /// order-node whose journal is on etcd (a primary, its standbys) reports where it
    /// stands (`<prefix>/<zid>`, a [`crate::fence::NodeFenceReport`]).
    pub fn node_fence(&self, node: &str) -> String {
        format!("{}/host/order-node/{node}/fence", self.prefix())
    }

    /// `holarchy/<cell>/host/order-node/*/fence/*`: every such order-node's processes.
    pub fn node_fence_all(&self) -> String {
        format!("{}/host/order-node/*/fence/*", self.prefix())
    }

    /// `holarchy/<cell>/host/order-node/<node>/orders`: a page of the node's orders
    /// (running and finished) for an [`crate::OrderListRequest`], answered with an
    /// [`crate::OrderPage`].
    pub fn node_listing(&self, node: &str) -> String {
        format!("{}/host/order-node/{node}/orders", self.prefix())
    }

    /// `holarchy/<cell>/host/order-node/<node>/held`: which orders the node holds
    /// ([`crate::held`]).
    pub fn node_held(&self, node: &str) -> String {
        format!("{}/host/order-node/{node}/held", self.prefix())
    }

    /// `holarchy/<cell>/host/order-node/*/held`: every node's held orders.
    pub fn node_held_all(&self) -> String {
        format!("{}/host/order-node/*/held", self.prefix())
    }

    /// `holarchy/<cell>/host/order-node/*/orders`: the first page of every node.
    pub fn node_listing_all(&self) -> String {
        format!("{}/host/order-node/*/orders", self.prefix())
    }

    /// `holarchy/<cell>/*/*/state`: the state of every holon.
    pub fn state_all(&self) -> String {
        format!("{}/*/*/state", self.prefix())
    }

    /// `holarchy/<cell>/resource/*/state`: every resource's state.
    pub fn resource_states(&self) -> String {
        format!("{}/resource/*/state", self.prefix())
    }

    /// `holarchy/<cell>/order/*/state`: every order's state.
    pub fn order_states(&self) -> String {
        format!("{}/order/*/state", self.prefix())
    }

    /// `holarchy/<cell>/host/<program>/<name>`: liveliness of a process that hosts holons
    /// or links them but is not one (an order-node; `cell up`'s router as
    /// `host/router/<host>`), so launchers can wait for it and dashboards show it.
    pub fn host(&self, program: &str, name: &str) -> String {
        format!("{}/host/{program}/{name}", self.prefix())
    }

    /// `holarchy/<cell>/host/*/*`: every process that hosts holons or links them (a
    /// router, an order-node).
    pub fn host_all(&self) -> String {
        format!("{}/host/*/*", self.prefix())
    }

    /// Recovers `(program, name)` from a `host/<program>/<name>` key of this cell.
    pub fn process_from_host<'k>(&self, key: &'k str) -> Option<(&'k str, &'k str)> {
        let rest = key.strip_prefix(&self.prefix())?.strip_prefix("/host/")?;
        let (program, name) = rest.split_once('/')?;
        (!program.is_empty() && !name.is_empty() && !name.contains('/')).then_some((program, name))
    }

    /// `holarchy/<cell>/resource/<name>/debug/crash`: fault injection, declared only when a
    /// holon is started with `--allow-fault-injection` (tests and demonstrations).
    pub fn debug_crash(&self, resource: &str) -> String {
        format!("{}/resource/{resource}/debug/crash", self.prefix())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn builds_the_key_space() {
        let keys = CellKeys::new("demo").unwrap();
        let robot = HolonId::resource("robot1").unwrap();
        assert_eq!(keys.alive(&robot), "holarchy/demo/alive/resource/robot1");
        assert_eq!(keys.alive_all(), "holarchy/demo/alive/**");
        assert_eq!(
            keys.alive_kind(HolonKind::Resource),
            "holarchy/demo/alive/resource/*"
        );
        assert_eq!(
            keys.holon_from_alive("holarchy/demo/alive/resource/robot1"),
            Some(robot.clone())
        );
        assert_eq!(
            keys.holon_from_alive("holarchy/other/alive/resource/r"),
            None
        );
        assert_eq!(keys.host("router", "h1"), "holarchy/demo/host/router/h1");
        assert_eq!(keys.host_all(), "holarchy/demo/host/*/*");
        assert_eq!(
            keys.process_from_host("holarchy/demo/host/order-node/orders1"),
            Some(("order-node", "orders1"))
        );
        assert_eq!(
            keys.process_from_host("holarchy/other/host/router/h1"),
            None
        );
        assert_eq!(keys.process_from_host("holarchy/demo/host/router"), None);
        assert_eq!(
            keys.service("robot1"),
            "holarchy/demo/resource/robot1/service"
        );
        assert_eq!(
            keys.outcome("robot1"),
            "holarchy/demo/resource/robot1/outcome"
        );
        assert_eq!(
            keys.offer("pick_n_place", "robot1"),
            "holarchy/demo/offer/pick_n_place/robot1"
        );
        assert_eq!(
            keys.offers("pick_n_place"),
            "holarchy/demo/offer/pick_n_place/*"
        );
        assert_eq!(keys.plan("breaker"), "holarchy/demo/product/breaker/plan");
        assert_eq!(keys.advice("planner"), "holarchy/demo/staff/planner/advice");
        assert_eq!(keys.inbox("o-17"), "holarchy/demo/order/o-17/inbox");
        assert_eq!(keys.orders_submit(), "holarchy/demo/orders/submit");
        assert_eq!(keys.state(&robot), "holarchy/demo/resource/robot1/state");
        assert_eq!(keys.state_all(), "holarchy/demo/*/*/state");
        assert!(CellKeys::new("Demo").is_err());
        assert!(CellKeys::new("a/b").is_err());
    }

    #[test]
    fn reply_keys_are_concrete_holarchy_keys() {
        validate_reply_key("holarchy/demo/order/o-17/inbox").unwrap();
        for bad in [
            "",
            "demo/order/o-17/inbox",
            "holarchy/demo/order/*/inbox",
            "holarchy/demo/**",
            "holarchy//x",
            "holarchy/demo/",
            "/holarchy/demo",
            "holarchy/de mo",
            "holarchy/$*",
            "holarchy/a?b",
        ] {
            assert!(validate_reply_key(bad).is_err(), "{bad:?} was accepted");
        }
        assert!(validate_reply_key(&format!("holarchy/{}", "a".repeat(600))).is_err());
    }
}
