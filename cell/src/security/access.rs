//! The cell's zenoh access control, generated from its identities (never written by
//! hand per host): what each role may send into the cell, keyed by the common name of
//! the certificate on the link. Every holon and router loads the same file and enforces
//! it on its own links (zenoh guards only a node's own links; peers link directly).
//!
//! | role | may declare (queryable, token, publication) | may query / subscribe |
//! |---|---|---|
//! | `resource.<r>` | `resource/<r>/{service,state,packml,carriers,outcome,layout,debug/crash,fence/*}`, `offer/*/<r>`, `alive/resource/<r>` | `order/*/inbox` (results), `host/order-node/*/held` (orders' presence), `resource/*/layout` (a transporter's moves), `alive/**` (twins, requesters' presence) |
//! | `product.<p>` | `product/<p>/{plan,state}`, `alive/product/<p>` | `alive/**` (twins) |
//! | `order-node.<n>` | `orders/submit`, `order/<n>-*/{inbox,state,cancel,part}`, `alive/order/<n>-*` (order-nodes of earlier releases), `host/order-node/<n>{,/fence/*,/orders,/held}` | `resource/*/{service,outcome,state}`, `offer/**`, `product/*/plan`, `staff/*/advice`, states, liveliness |
//! | `staff.<s>` | `staff/<s>/{advice,state}`, `alive/staff/<s>` | states, plans, liveliness (it advises; it books nothing) |
//! | `operator.<o>` | nothing | `orders/submit`, `order/*/{cancel,part}` (a lost part's place), `resource/*/packml` (PackML commands), `resource/*/carriers` (a conveyor's carrier out or back), states, plans, liveliness |
//! | `observer.<o>` | nothing | states, plans, the layout (`resource/*/layout`), liveliness |
//! | `router.<h>` | everything (routers forward for others; trusted) | everything |
//! | `etcd.<h>` | nothing (an etcd member, not a zenoh client: not even listed) | nothing |
//!
//! Every holon role also declares and queries its own `takeover/<role>/<name>`: a
//! successor holding the same identity asks the running process to hand over (an
//! upgrade, [`holon::takeover`]); no other identity can replace it.
//!
//! Every rule is an ingress rule: it limits what a link may bring in. Anything may go
//! out to a known identity (egress), since what reaches a link is only what it asked
//! for. An identity not listed (a certificate of the cell CA issued after the running
//! processes loaded the file) matches no subject and is denied everything.

use serde_json::{json, Value};

pub use holon::role::{parse_identity, Role};

const DECLARE: &[&str] = &["declare_queryable", "reply"];
const READ: &[&str] = &[
    "query",
    "declare_subscriber",
    "declare_liveliness_subscriber",
    "liveliness_query",
];
const ALL: &[&str] = &[
    "put",
    "delete",
    "declare_subscriber",
    "query",
    "declare_queryable",
    "reply",
    "liveliness_token",
    "declare_liveliness_subscriber",
    "liveliness_query",
];

/// One rule: the messages it allows, on key expressions under `holarchy/<cell>/`.
type Rule = (&'static [&'static str], Vec<String>);

/// The rules of one identity: (messages, key expressions under `holarchy/<cell>/`).
fn grants(role: Role, name: &str) -> Vec<Rule> {
    let mut rules = match role {
        Role::Resource => resource(name),
        Role::Product => product(name),
        Role::OrderNode => order_node(name),
        Role::Staff => staff(name),
        Role::Operator => vec![(READ, {
            let mut keys = reading();
            keys.extend([
                "orders/submit".to_string(),
                "order/*/cancel".to_string(),
                "order/*/part".to_string(),
                "resource/*/packml".to_string(),
                // A conveyor's carrier out of service or back.
                "resource/*/carriers".to_string(),
            ]);
            keys
        })],
        Role::Observer => vec![(READ, reading())],
        Role::Router => vec![(ALL, vec!["**".to_string()])],
        // An etcd member's certificate is for etcd's links only.
        Role::Etcd => Vec::new(),
    };
    match role {
        Role::Resource => rules.push(takeover("resource", name)),
        Role::Product => rules.push(takeover("product", name)),
        Role::OrderNode => rules.push(takeover("order-node", name)),
        Role::Staff => rules.push(takeover("staff", name)),
        Role::Operator | Role::Observer | Role::Router | Role::Etcd => {}
    }
    rules
}

/// What every reader may read: states, plans, presence.
fn reading() -> Vec<String> {
    vec![
        "*/*/state".to_string(),
        // Which process holds a fenced resource's controller, and its standbys.
        "resource/*/fence/*".to_string(),
        // The cell's layout, each resource's part.
        "resource/*/layout".to_string(),
        "product/*/plan".to_string(),
        "alive/**".to_string(),
        "host/**".to_string(),
    ]
}

/// A successor (the same identity) asks the running process to hand over.
fn takeover(role: &str, name: &str) -> Rule {
    (
        &["declare_queryable", "reply", "query"][..],
        vec![format!("takeover/{role}/{name}")],
    )
}

/// A resource holon's rules.
fn resource(name: &str) -> Vec<Rule> {
    vec![
        (
            DECLARE,
            vec![
                format!("resource/{name}/service"),
                format!("resource/{name}/state"),
                format!("resource/{name}/packml"),
                // A conveyor's: an operator's word on its carriers.
                format!("resource/{name}/carriers"),
                // What became of a conversation, asked by the order that booked it.
                format!("resource/{name}/outcome"),
                // Its part of the cell's layout.
                format!("resource/{name}/layout"),
                format!("resource/{name}/debug/crash"),
                format!("resource/{name}/fence/*"),
                format!("offer/*/{name}"),
            ],
        ),
        (
            &["put"],
            vec![
                format!("resource/{name}/state"),
                format!("resource/{name}/fence/*"),
            ],
        ),
        (
            &["liveliness_token"],
            vec![format!("alive/resource/{name}")],
        ),
        // Who holds the name (answered on the token's key).
        (DECLARE, vec![format!("alive/resource/{name}")]),
        (&["query"], vec!["order/*/inbox".to_string()]),
        // Which orders the order-nodes hold (the orders' bookings' lifetime).
        (&["query"], vec!["host/order-node/*/held".to_string()]),
        // The cell's layout (a transporter times its moves by it).
        (&["query"], vec!["resource/*/layout".to_string()]),
        // Twins and requesters' presence (the bookings' lifetime).
        (
            &["query", "declare_liveliness_subscriber", "liveliness_query"],
            vec!["alive/**".to_string()],
        ),
    ]
}

/// A product holon's rules.
fn product(name: &str) -> Vec<Rule> {
    vec![
        (
            DECLARE,
            vec![
                format!("product/{name}/plan"),
                format!("product/{name}/state"),
            ],
        ),
        (&["put"], vec![format!("product/{name}/state")]),
        (&["liveliness_token"], vec![format!("alive/product/{name}")]),
        (DECLARE, vec![format!("alive/product/{name}")]),
        (
            &["query", "liveliness_query", "declare_liveliness_subscriber"],
            vec!["alive/**".to_string()],
        ),
    ]
}

/// An order-node's rules.
fn order_node(name: &str) -> Vec<Rule> {
    vec![
        (
            DECLARE,
            vec![
                "orders/submit".to_string(),
                format!("host/order-node/{name}"),
                // Where each of its processes stands on etcd (holder or standby).
                format!("host/order-node/{name}/fence/*"),
                // Its orders listed a page at a time.
                format!("host/order-node/{name}/orders"),
                // Which of its orders it holds (asked by resources).
                format!("host/order-node/{name}/held"),
                format!("order/{name}-$*/inbox"),
                format!("order/{name}-$*/state"),
                format!("order/{name}-$*/cancel"),
                // Operators' words on where its orders' lost parts are.
                format!("order/{name}-$*/part"),
            ],
        ),
        (&["put"], vec![format!("order/{name}-$*/state")]),
        (
            &["liveliness_token"],
            vec![
                // Orders of an order-node of an earlier release held a token each.
                format!("alive/order/{name}-$*"),
                format!("host/order-node/{name}"),
            ],
        ),
        (READ, {
            let mut keys = reading();
            keys.extend([
                "resource/*/service".to_string(),
                "resource/*/outcome".to_string(),
                "offer/**".to_string(),
                "staff/*/advice".to_string(),
            ]);
            keys
        }),
    ]
}

/// A staff holon's rules.
fn staff(name: &str) -> Vec<Rule> {
    vec![
        (
            DECLARE,
            vec![
                format!("staff/{name}/advice"),
                format!("staff/{name}/state"),
                // Who holds the name (answered on the token's key).
                format!("alive/staff/{name}"),
            ],
        ),
        (&["put"], vec![format!("staff/{name}/state")]),
        (&["liveliness_token"], vec![format!("alive/staff/{name}")]),
        (READ, reading()),
    ]
}

/// The `access_control` section for a cell and its identities, as a zenoh config
/// (`{"access_control": {...}}`): default deny, one subject per identity. An etcd
/// member's identity is left out: it is no subject, so zenoh denies it everything.
pub fn access_control(cell: &str, identities: &[String]) -> anyhow::Result<Value> {
    let mut rules = vec![json!({
        "id": "egress",
        "messages": ALL,
        "flows": ["egress"],
        "permission": "allow",
        "key_exprs": ["**"],
    })];
    let mut subjects = Vec::new();
    let mut policies = Vec::new();
    for identity in identities {
        let (role, name) = parse_identity(identity)?;
        if role == Role::Etcd {
            continue;
        }
        subjects.push(json!({ "id": identity, "cert_common_names": [identity] }));
        let mut rule_ids = vec!["egress".to_string()];
        for (index, (messages, keys)) in grants(role, name).into_iter().enumerate() {
            let id = format!("{identity}/{index}");
            let keys: Vec<String> = keys
                .into_iter()
                .map(|k| {
                    if k == "**" {
                        k
                    } else {
                        format!("{}/{cell}/{k}", schemas::keys::ROOT)
                    }
                })
                .collect();
            rules.push(json!({
                "id": id,
                "messages": messages,
                "flows": ["ingress"],
                "permission": "allow",
                "key_exprs": keys,
            }));
            rule_ids.push(id);
        }
        policies.push(json!({ "id": identity, "rules": rule_ids, "subjects": [identity] }));
    }
    Ok(json!({
        "access_control": {
            "enabled": true,
            "default_permission": "deny",
            "rules": rules,
            "subjects": subjects,
            "policies": policies,
        }
    }))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn identities_are_role_dot_name() {
        assert_eq!(
            parse_identity("resource.robot1").unwrap(),
            (Role::Resource, "robot1")
        );
        assert_eq!(
            parse_identity("order-node.orders1").unwrap().0,
            Role::OrderNode
        );
        for bad in ["robot1", "robot.robot1", "resource.", "resource.Robot1"] {
            assert!(parse_identity(bad).is_err(), "{bad}");
        }
    }

    #[test]
    fn the_generated_access_control_is_a_valid_zenoh_config() {
        let identities: Vec<String> = [
            "router.local",
            "resource.robot1",
            "product.breaker",
            "order-node.orders1",
            "staff.planner",
            "operator.default",
            "observer.default",
        ]
        .map(String::from)
        .to_vec();
        let value = access_control("demo", &identities).unwrap();
        let mut config = zenoh::Config::default();
        config
            .insert_json5("access_control", &value["access_control"].to_string())
            .unwrap();
        let text = value.to_string();
        assert!(
            text.contains("holarchy/demo/resource/robot1/service"),
            "{text}"
        );
        assert!(
            text.contains("holarchy/demo/order/orders1-$*/inbox"),
            "{text}"
        );
        assert!(
            text.contains("holarchy/demo/staff/planner/advice"),
            "{text}"
        );
        assert!(text.contains("holarchy/demo/staff/*/advice"), "{text}");
    }

    #[test]
    fn only_a_staff_identity_may_answer_advice_and_only_its_own() {
        let declares = |role, name| -> Vec<String> {
            grants(role, name)
                .into_iter()
                .filter(|(messages, _)| messages.contains(&"declare_queryable"))
                .flat_map(|(_, keys)| keys)
                .collect()
        };
        for (role, name) in [
            (Role::OrderNode, "orders1"),
            (Role::Resource, "robot1"),
            (Role::Product, "breaker"),
        ] {
            let keys = declares(role, name);
            assert!(
                keys.iter().all(|k| !k.starts_with("staff/")),
                "{role:?} may answer as a staff: {keys:?}"
            );
        }
        let staff = declares(Role::Staff, "planner");
        assert!(staff.contains(&"staff/planner/advice".to_string()));
        assert!(staff.iter().all(|k| k.contains("planner")), "{staff:?}");
        // The staff books nothing: it may not ask a resource's service.
        let asks: Vec<String> = grants(Role::Staff, "planner")
            .into_iter()
            .filter(|(messages, _)| messages.contains(&"query"))
            .flat_map(|(_, keys)| keys)
            .collect();
        assert!(asks.iter().all(|k| !k.contains("service")), "{asks:?}");
    }

    #[test]
    fn an_order_node_answers_its_own_fence_reports_and_readers_read_every_one() {
        let keys = |role, name, message: &str| -> Vec<String> {
            grants(role, name)
                .into_iter()
                .filter(|(messages, _)| messages.contains(&message))
                .flat_map(|(_, keys)| keys)
                .collect()
        };
        let answers = keys(Role::OrderNode, "orders1", "declare_queryable");
        assert!(answers.contains(&"host/order-node/orders1/fence/*".to_string()));
        assert!(answers.contains(&"host/order-node/orders1/orders".to_string()));
        assert!(answers.contains(&"host/order-node/orders1/held".to_string()));
        assert!(
            answers
                .iter()
                .all(|k| !k.contains("fence") || k.contains("orders1")),
            "{answers:?}"
        );
        // A resource asks every node which orders it holds.
        assert!(
            keys(Role::Resource, "robot1", "query").contains(&"host/order-node/*/held".to_string())
        );
        // `cell status` and the dashboard ask `host/order-node/*/fence/*`: `host/**`.
        for (role, name) in [(Role::Operator, "default"), (Role::Observer, "default")] {
            assert!(keys(role, name, "query").contains(&"host/**".to_string()));
            assert!(keys(role, name, "declare_queryable").is_empty());
        }
    }

    #[test]
    fn only_operators_may_command_a_resource_and_only_a_resource_answers() {
        let may = |role, name, message: &str| -> Vec<String> {
            grants(role, name)
                .into_iter()
                .filter(|(messages, _)| messages.contains(&message))
                .flat_map(|(_, keys)| keys)
                .filter(|k| k.ends_with("/packml") || k == "**")
                .collect()
        };
        assert_eq!(
            may(Role::Operator, "default", "query"),
            ["resource/*/packml"]
        );
        for (role, name) in [
            (Role::Observer, "default"),
            (Role::Resource, "robot1"),
            (Role::OrderNode, "orders1"),
            (Role::Staff, "planner"),
            (Role::Product, "breaker"),
        ] {
            assert!(
                may(role, name, "query").is_empty(),
                "{role:?} may command resources"
            );
        }
        assert_eq!(
            may(Role::Resource, "robot1", "declare_queryable"),
            ["resource/robot1/packml"]
        );
        assert!(may(Role::Operator, "default", "declare_queryable").is_empty());
    }
}
