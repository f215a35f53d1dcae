//! The JSON of etcd's v3 gateway (`/v3/...`), as etcd 3.4 speaks it: keys and values in
//! base64, int64 and uint64 fields as JSON strings, and fields at their default value
//! (0, false, empty) left out of replies.

use base64::Engine;
use serde::{Deserialize, Deserializer, Serialize, Serializer};

/// Bytes written as base64, as the gateway wants keys and values.
#[derive(Debug, Clone, Default, PartialEq, Eq)]
pub(crate) struct Base64(pub Vec<u8>);

impl Serialize for Base64 {
    fn serialize<S: Serializer>(&self, s: S) -> Result<S::Ok, S::Error> {
        s.serialize_str(&base64::engine::general_purpose::STANDARD.encode(&self.0))
    }
}

impl<'de> Deserialize<'de> for Base64 {
    fn deserialize<D: Deserializer<'de>>(d: D) -> Result<Self, D::Error> {
        let text = String::deserialize(d)?;
        base64::engine::general_purpose::STANDARD
            .decode(text.as_bytes())
            .map(Base64)
            .map_err(serde::de::Error::custom)
    }
}

impl From<&str> for Base64 {
    fn from(text: &str) -> Self {
        Base64(text.as_bytes().to_vec())
    }
}

/// An int64 or uint64 field: written as a JSON string, read from a string or a number.
pub(crate) mod int {
    use serde::{Deserialize, Deserializer, Serializer};

    pub fn serialize<S: Serializer, N: std::fmt::Display>(n: &N, s: S) -> Result<S::Ok, S::Error> {
        s.serialize_str(&n.to_string())
    }

    pub fn deserialize<'de, D, N>(d: D) -> Result<N, D::Error>
    where
        D: Deserializer<'de>,
        N: std::str::FromStr,
        N::Err: std::fmt::Display,
    {
        #[derive(Deserialize)]
        #[serde(untagged)]
        enum Either {
            Text(String),
            Number(serde_json::Number),
        }
        let text = match Either::deserialize(d)? {
            Either::Text(text) => text,
            Either::Number(n) => n.to_string(),
        };
        text.parse().map_err(serde::de::Error::custom)
    }
}

/// What every reply starts with.
#[derive(Debug, Clone, Default, Deserialize)]
pub(crate) struct Header {
    /// The store's revision when the request was served (for a write: the write's).
    #[serde(default, with = "int")]
    pub revision: i64,
    /// The member that served the request.
    #[serde(default, with = "int")]
    pub member_id: u64,
}

/// One key as etcd holds it.
#[derive(Debug, Clone, Default, Deserialize)]
pub(crate) struct KeyValue {
    /// The key.
    pub key: Base64,
    /// The revision that created it (since it last did not exist).
    #[serde(default, with = "int")]
    pub create_revision: i64,
    /// The revision that last changed it.
    #[serde(default, with = "int")]
    pub mod_revision: i64,
    /// Its value.
    #[serde(default)]
    pub value: Base64,
    /// The lease it is attached to (0: none).
    #[serde(default, with = "int")]
    pub lease: i64,
}

/// `/v3/kv/range`.
#[derive(Debug, Clone, Default, Serialize)]
pub(crate) struct RangeRequest {
    /// The key, or the first of the range.
    pub key: Base64,
    /// Every key in `[key, range_end)`; absent: `key` alone.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub range_end: Option<Base64>,
    /// At most this many keys (0: no limit).
    #[serde(with = "int", skip_serializing_if = "is_zero")]
    pub limit: i64,
    /// Read at this revision (0: the newest).
    #[serde(with = "int", skip_serializing_if = "is_zero")]
    pub revision: i64,
    /// Only keys last changed at this revision or later (0: any).
    #[serde(with = "int", skip_serializing_if = "is_zero")]
    pub min_mod_revision: i64,
    /// `ASCEND` or `DESCEND` (absent: etcd's default, by key).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub sort_order: Option<&'static str>,
    /// What to sort on: `KEY`, `MOD` (the last change's revision), ... (absent: `KEY`).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub sort_target: Option<&'static str>,
}

fn is_zero(n: &i64) -> bool {
    *n == 0
}

/// The reply to a range.
#[derive(Debug, Clone, Default, Deserialize)]
pub(crate) struct RangeResponse {
    /// The reply's header.
    #[serde(default)]
    pub header: Header,
    /// The keys found, in key order.
    #[serde(default)]
    pub kvs: Vec<KeyValue>,
    /// Whether more keys are in the range than `limit` let through.
    #[serde(default)]
    pub more: bool,
}

/// A put, inside a txn.
#[derive(Debug, Clone, Default, Serialize)]
pub(crate) struct PutRequest {
    /// The key.
    pub key: Base64,
    /// The value.
    pub value: Base64,
    /// Attached to this lease (0: none).
    #[serde(with = "int", skip_serializing_if = "is_zero")]
    pub lease: i64,
}

/// A delete, inside a txn.
#[derive(Debug, Clone, Default, Serialize)]
pub(crate) struct DeleteRangeRequest {
    /// The key, or the first of the range.
    pub key: Base64,
    /// Every key in `[key, range_end)`; absent: `key` alone.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub range_end: Option<Base64>,
}

/// One operation of a txn.
#[derive(Debug, Clone, Serialize)]
pub(crate) enum RequestOp {
    /// A read.
    #[serde(rename = "request_range")]
    Range(RangeRequest),
    /// A write.
    #[serde(rename = "request_put")]
    Put(PutRequest),
    /// A delete.
    #[serde(rename = "request_delete_range")]
    Delete(DeleteRangeRequest),
}

/// The reply to one operation of a txn (only ranges are read back).
#[derive(Debug, Clone, Default, Deserialize)]
pub(crate) struct ResponseOp {
    /// A range's reply (absent for a put's or a delete's).
    #[serde(default)]
    pub response_range: Option<RangeResponse>,
}

/// A txn's condition: here always "the key's create_revision equals".
#[derive(Debug, Clone, Serialize)]
pub(crate) struct Compare {
    /// The key compared.
    pub key: Base64,
    /// `CREATE`: the key's create_revision (0 for a key that does not exist).
    pub target: &'static str,
    /// `EQUAL`.
    pub result: &'static str,
    /// The create_revision the key must have.
    #[serde(with = "int")]
    pub create_revision: i64,
}

impl Compare {
    /// True when `key`'s create_revision is `revision` (0: the key does not exist).
    pub fn created_at(key: Base64, revision: i64) -> Compare {
        Compare {
            key,
            target: "CREATE",
            result: "EQUAL",
            create_revision: revision,
        }
    }
}

/// `/v3/kv/txn`: `success` if every compare holds, else `failure`, in one commit.
#[derive(Debug, Clone, Default, Serialize)]
pub(crate) struct TxnRequest {
    /// The conditions, all of which must hold.
    pub compare: Vec<Compare>,
    /// Done if they hold.
    pub success: Vec<RequestOp>,
    /// Done if they do not.
    pub failure: Vec<RequestOp>,
}

/// The reply to a txn.
#[derive(Debug, Clone, Default, Deserialize)]
pub(crate) struct TxnResponse {
    /// The reply's header (its revision: the txn's, if it wrote).
    #[serde(default)]
    pub header: Header,
    /// Whether the compares held (absent, hence false, when they did not).
    #[serde(default)]
    pub succeeded: bool,
    /// The replies to the branch's operations, in order.
    #[serde(default)]
    pub responses: Vec<ResponseOp>,
}

/// `/v3/lease/grant`.
#[derive(Debug, Clone, Serialize)]
pub(crate) struct LeaseGrantRequest {
    /// Seconds to live.
    #[serde(rename = "TTL", with = "int")]
    pub ttl: i64,
}

/// The reply to a grant, and a keep-alive's `result`.
#[derive(Debug, Clone, Default, Deserialize)]
pub(crate) struct LeaseResponse {
    /// The lease's id.
    #[serde(rename = "ID", default, with = "int")]
    pub id: i64,
    /// Seconds left; absent (0) in a keep-alive's reply when the lease is gone.
    #[serde(rename = "TTL", default, with = "int")]
    pub ttl: i64,
}

/// `/v3/lease/keepalive` and `/v3/lease/revoke`.
#[derive(Debug, Clone, Serialize)]
pub(crate) struct LeaseIdRequest {
    /// The lease's id.
    #[serde(rename = "ID", with = "int")]
    pub id: i64,
}

/// The keep-alive stream's one reply to a one-request body.
#[derive(Debug, Clone, Default, Deserialize)]
pub(crate) struct KeepAliveResponse {
    /// The renewed lease.
    #[serde(default)]
    pub result: LeaseResponse,
}

/// `/v3/maintenance/status`.
#[derive(Debug, Clone, Default, Deserialize)]
pub(crate) struct StatusResponse {
    /// The reply's header (its member_id: the member asked).
    #[serde(default)]
    pub header: Header,
    /// The raft leader's member id, as this member knows it (0: none).
    #[serde(default, with = "int")]
    pub leader: u64,
}

/// An error reply (HTTP status not 200): gRPC's code and etcd's message.
#[derive(Debug, Clone, Default, Deserialize)]
pub(crate) struct ErrorReply {
    /// etcd's message.
    #[serde(default)]
    pub message: String,
    /// The gRPC status code.
    #[serde(default)]
    pub code: i32,
}

/// The end of the range of every key starting with `prefix` (its last byte below 0xff
/// incremented, what follows dropped); `\0` (every key) for a prefix of only 0xff.
pub(crate) fn prefix_end(prefix: &[u8]) -> Vec<u8> {
    let mut end = prefix.to_vec();
    while let Some(last) = end.pop() {
        if last < 0xff {
            end.push(last + 1);
            return end;
        }
    }
    vec![0]
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn etcd_replies_decode_as_the_gateway_writes_them() {
        // Replies of etcd 3.4.23's gateway, copied from a run.
        let won: TxnResponse = serde_json::from_str(
            r#"{"header":{"cluster_id":"324952591200643719","member_id":"3319814642761637952","revision":"3","raft_term":"2"},"succeeded":true,"responses":[{"response_put":{"header":{"revision":"3"}}}]}"#,
        )
        .unwrap();
        assert!(won.succeeded);
        assert_eq!(won.header.revision, 3);
        assert_eq!(won.header.member_id, 3319814642761637952);
        let lost: TxnResponse = serde_json::from_str(
            r#"{"header":{"revision":"3"},"responses":[{"response_range":{"header":{"revision":"3"},"kvs":[{"key":"cC9sZWFkZXI=","create_revision":"3","mod_revision":"3","version":"1","value":"YQ==","lease":"2324035578911004171"}],"count":"1"}}]}"#,
        )
        .unwrap();
        assert!(!lost.succeeded);
        let holder = &lost.responses[0].response_range.as_ref().unwrap().kvs[0];
        assert_eq!(holder.key.0, b"p/leader");
        assert_eq!(holder.create_revision, 3);
        assert_eq!(holder.value.0, b"a");
        assert_eq!(holder.lease, 2324035578911004171);
        let gone: KeepAliveResponse = serde_json::from_str(
            r#"{"result":{"header":{"revision":"4"},"ID":"2324035578911004171"}}"#,
        )
        .unwrap();
        assert_eq!(gone.result.ttl, 0, "a lease gone has no TTL");
        let empty: RangeResponse = serde_json::from_str(r#"{"header":{"revision":"4"}}"#).unwrap();
        assert!(empty.kvs.is_empty());
    }

    #[test]
    fn requests_are_written_as_the_gateway_reads_them() {
        let txn = TxnRequest {
            compare: vec![Compare::created_at("p/leader".into(), 7)],
            success: vec![RequestOp::Put(PutRequest {
                key: "k".into(),
                value: "v".into(),
                lease: 0,
            })],
            failure: vec![RequestOp::Range(RangeRequest {
                key: "p/leader".into(),
                ..Default::default()
            })],
        };
        assert_eq!(
            serde_json::to_string(&txn).unwrap(),
            r#"{"compare":[{"key":"cC9sZWFkZXI=","target":"CREATE","result":"EQUAL","create_revision":"7"}],"success":[{"request_put":{"key":"aw==","value":"dg=="}}],"failure":[{"request_range":{"key":"cC9sZWFkZXI="}}]}"#
        );
    }

    #[test]
    fn a_prefix_ends_where_its_keys_do() {
        assert_eq!(prefix_end(b"a/journal/order/"), b"a/journal/order0");
        assert_eq!(prefix_end(b"a\xff"), b"b");
        assert_eq!(prefix_end(b"\xff"), b"\0");
    }
}
