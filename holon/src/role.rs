//! Who a process is in a secure cell: its identity, `<role>.<name>`, the common name
//! of its certificate, and the role that decides what the cell's access control lets
//! it do. One enum for every crate: the holons name themselves with it, `cell certs`
//! issues by it, the access control and the dashboard read it back.

use std::fmt;

use schemas::HolonKind;

/// What the first part of an identity says.
#[derive(Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord, Hash)]
pub enum Role {
    /// A resource holon (`resource.robot1`).
    Resource,
    /// A product holon (`product.breaker`).
    Product,
    /// An order-node, host of order holons (`order-node.orders1`).
    OrderNode,
    /// A staff holon (`staff.planner`).
    Staff,
    /// A person or tool that operates the cell (`operator.anna`).
    Operator,
    /// A person or screen that only watches (`observer.wall`).
    Observer,
    /// A zenoh router (`router.hostA`).
    Router,
    /// An etcd member (`etcd.hostB`): its server certificate for the order-nodes'
    /// journal, and its client certificate on its peer links. Not a zenoh client: the
    /// cell's access control gives it nothing.
    Etcd,
}

impl Role {
    /// Every role, in the order the docs list them.
    pub const ALL: [Role; 8] = [
        Role::Resource,
        Role::Product,
        Role::OrderNode,
        Role::Staff,
        Role::Operator,
        Role::Observer,
        Role::Router,
        Role::Etcd,
    ];

    /// The word of the identity.
    pub fn as_str(self) -> &'static str {
        match self {
            Role::Resource => "resource",
            Role::Product => "product",
            Role::OrderNode => "order-node",
            Role::Staff => "staff",
            Role::Operator => "operator",
            Role::Observer => "observer",
            Role::Router => "router",
            Role::Etcd => "etcd",
        }
    }

    /// The role of a word, if it is one.
    pub fn parse(text: &str) -> Option<Role> {
        Role::ALL.into_iter().find(|role| role.as_str() == text)
    }

    /// The role a holon of `kind` runs as: orders run inside their order-node, which
    /// has the identity.
    pub fn of_holon(kind: HolonKind) -> Role {
        match kind {
            HolonKind::Resource => Role::Resource,
            HolonKind::Product => Role::Product,
            HolonKind::Order => Role::OrderNode,
            HolonKind::Staff => Role::Staff,
        }
    }
}

impl fmt::Display for Role {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(self.as_str())
    }
}

/// Why a text is not an identity.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum IdentityError {
    #[error("identity {0:?} is not <role>.<name> (e.g. resource.robot1)")]
    NoRole(String),
    #[error("identity {identity:?}: the role {role:?} is not resource, product, order-node, staff, operator, observer, router or etcd")]
    UnknownRole { identity: String, role: String },
    #[error("identity {identity:?}: {why}")]
    BadName { identity: String, why: String },
}

/// The identity (certificate common name) of a process: `<role>.<name>`.
pub fn identity(role: Role, name: &str) -> String {
    format!("{role}.{name}")
}

/// Splits `<role>.<name>` and checks both parts.
pub fn parse_identity(identity: &str) -> Result<(Role, &str), IdentityError> {
    let (role, name) = identity
        .split_once('.')
        .ok_or_else(|| IdentityError::NoRole(identity.to_string()))?;
    let role = Role::parse(role).ok_or_else(|| IdentityError::UnknownRole {
        identity: identity.to_string(),
        role: role.to_string(),
    })?;
    schemas::validate_name("identity name", name).map_err(|e| IdentityError::BadName {
        identity: identity.to_string(),
        why: e.to_string(),
    })?;
    Ok((role, name))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn identities_round_trip_and_nonsense_is_refused() {
        for role in Role::ALL {
            let id = identity(role, "x1");
            assert_eq!(parse_identity(&id), Ok((role, "x1")));
        }
        assert_eq!(identity(Role::OrderNode, "orders1"), "order-node.orders1");
        assert!(matches!(
            parse_identity("nonsense"),
            Err(IdentityError::NoRole(_))
        ));
        assert!(matches!(
            parse_identity("pilot.anna"),
            Err(IdentityError::UnknownRole { .. })
        ));
        assert!(matches!(
            parse_identity("operator.an na"),
            Err(IdentityError::BadName { .. })
        ));
    }
}
