//! The fenced record store: records of JSON addressed by a kind and an id, as in
//! [`crate::journal::Journal`], kept in etcd under `<prefix>/journal/<kind>/<id>`.
//!
//! **The fence**: every write is one txn whose only condition is that the leader key
//! `<prefix>/leader` still has the create_revision the writer won it at (its epoch). A
//! holder whose lease expired or was revoked, whoever holds the key since, finds the
//! condition false: the write changes nothing and fails with [`EtcdError::Deposed`]. A
//! write returns `Ok` only once etcd committed it, i.e. once it is on a majority of the
//! members' disks (etcd fsyncs its log before it acknowledges).
//!
//! Reads are linearizable and not fenced: a standby reads what the holder wrote.

use serde::de::DeserializeOwned;
use serde::Serialize;
use tokio::sync::watch;

use super::client::Retry;
use super::leadership::{describe, holder_in, leader_key, Leadership};
use super::wire::{self, Base64, Compare, DeleteRangeRequest, PutRequest, RangeRequest, RequestOp};
use super::{Client, EtcdError};

/// The most records one write may hold: etcd's default `--max-txn-ops` (128), less
/// nothing (the fence is a compare, not an operation).
pub const MAX_RECORDS_PER_WRITE: usize = 128;

/// How many keys a list reads per request.
const PAGE: i64 = 500;

/// Records of one holon in etcd, written only by the holder of its leader key at one
/// epoch.
#[derive(Debug, Clone)]
pub struct FencedStore {
    /// The cluster.
    client: Client,
    /// The holon's key prefix.
    prefix: String,
    /// The leader key's create_revision every write is conditional on.
    epoch: i64,
    /// The holder's standing, when the store came from a [`super::Leader`]: once
    /// deposed, writes are refused without asking etcd.
    leadership: Option<watch::Receiver<Leadership>>,
}

impl FencedStore {
    /// The store under `prefix`, writing only while `<prefix>/leader` was created at
    /// `epoch`. ([`super::Leader::store`] gives one that also knows when its holder is
    /// deposed.)
    pub fn new(client: Client, prefix: &str, epoch: i64) -> FencedStore {
        FencedStore {
            client,
            prefix: prefix.to_string(),
            epoch,
            leadership: None,
        }
    }

    pub(crate) fn with_leadership(mut self, state: watch::Receiver<Leadership>) -> FencedStore {
        self.leadership = Some(state);
        self
    }

    /// The epoch the writes are fenced on.
    pub fn epoch(&self) -> i64 {
        self.epoch
    }

    /// The etcd key of a record: `<prefix>/journal/<kind>/<id>`.
    pub fn key(&self, kind: &str, id: &str) -> String {
        format!("{}/journal/{kind}/{id}", self.prefix)
    }

    /// Writes one record; `Ok` once etcd committed it.
    pub async fn put<T: Serialize>(
        &self,
        kind: &str,
        id: &str,
        value: &T,
    ) -> Result<(), EtcdError> {
        self.put_all([(kind, id, value)]).await
    }

    /// Writes several records (`(kind, id, value)`) in one commit: all or none.
    pub async fn put_all<'a, T, I>(&self, records: I) -> Result<(), EtcdError>
    where
        T: Serialize + 'a,
        I: IntoIterator<Item = (&'a str, &'a str, &'a T)>,
    {
        let mut operations = Vec::new();
        for (kind, id, value) in records {
            check_names(kind, id)?;
            let body = serde_json::to_vec(value).expect("journal records serialize");
            operations.push(RequestOp::Put(PutRequest {
                key: self.key(kind, id).as_str().into(),
                value: Base64(body),
                lease: 0,
            }));
        }
        self.write(operations).await
    }

    /// Removes records of `kind` (no error for one that is absent), in one commit: all
    /// are gone or none is.
    pub async fn delete<I, S>(&self, kind: &str, ids: I) -> Result<(), EtcdError>
    where
        I: IntoIterator<Item = S>,
        S: AsRef<str>,
    {
        let mut operations = Vec::new();
        for id in ids {
            check_names(kind, id.as_ref())?;
            operations.push(RequestOp::Delete(DeleteRangeRequest {
                key: self.key(kind, id.as_ref()).as_str().into(),
                range_end: None,
            }));
        }
        self.write(operations).await
    }

    /// One fenced txn of `operations`.
    async fn write(&self, operations: Vec<RequestOp>) -> Result<(), EtcdError> {
        let key = leader_key(&self.prefix);
        if operations.is_empty() {
            return Ok(());
        }
        if operations.len() > MAX_RECORDS_PER_WRITE {
            return Err(EtcdError::TooLarge {
                count: operations.len(),
                max: MAX_RECORDS_PER_WRITE,
            });
        }
        if let Some(state) = &self.leadership {
            if let Leadership::Deposed { why, .. } = &*state.borrow() {
                return Err(EtcdError::Deposed {
                    key,
                    epoch: self.epoch,
                    holder: format!("stepped down: {why}"),
                });
            }
        }
        let txn = wire::TxnRequest {
            compare: vec![Compare::created_at(key.as_str().into(), self.epoch)],
            success: operations,
            failure: vec![RequestOp::Range(RangeRequest {
                key: key.as_str().into(),
                ..Default::default()
            })],
        };
        let reply: wire::TxnResponse = self
            .client
            .call("/v3/kv/txn", &txn, Retry::IfNotSent)
            .await?;
        if reply.succeeded {
            return Ok(());
        }
        let holder = holder_in(&reply);
        tracing::warn!(key = %key, epoch = self.epoch, holder = ?holder, "write refused: deposed");
        Err(EtcdError::Deposed {
            key,
            epoch: self.epoch,
            holder: describe(holder.as_ref()),
        })
    }

    /// Reads one record.
    pub async fn get<T: DeserializeOwned>(
        &self,
        kind: &str,
        id: &str,
    ) -> Result<Option<T>, EtcdError> {
        check_names(kind, id)?;
        let key = self.key(kind, id);
        let range = RangeRequest {
            key: key.as_str().into(),
            ..Default::default()
        };
        let reply: wire::RangeResponse = self
            .client
            .call("/v3/kv/range", &range, Retry::Always)
            .await?;
        reply
            .kvs
            .first()
            .map(|kv| decode(&key, &kv.value.0))
            .transpose()
    }

    /// Reads the records of `kind` with these ids, in the order asked; absent ones are
    /// left out.
    pub async fn get_many<T, I, S>(&self, kind: &str, ids: I) -> Result<Vec<(String, T)>, EtcdError>
    where
        T: DeserializeOwned,
        I: IntoIterator<Item = S>,
        S: AsRef<str>,
    {
        let mut found = Vec::new();
        for id in ids {
            if let Some(value) = self.get(kind, id.as_ref()).await? {
                found.push((id.as_ref().to_string(), value));
            }
        }
        Ok(found)
    }

    /// Every record of a kind, by id (in the order of their keys' bytes), read at one
    /// revision however many pages it takes.
    pub async fn list<T: DeserializeOwned>(
        &self,
        kind: &str,
    ) -> Result<Vec<(String, T)>, EtcdError> {
        check_names(kind, "-")?;
        let prefix = format!("{}/journal/{kind}/", self.prefix);
        let end = wire::prefix_end(prefix.as_bytes());
        let mut records = Vec::new();
        let mut from = prefix.as_bytes().to_vec();
        let mut revision = 0;
        loop {
            let range = RangeRequest {
                key: Base64(from.clone()),
                range_end: Some(Base64(end.clone())),
                limit: PAGE,
                revision,
                ..Default::default()
            };
            let reply: wire::RangeResponse = self
                .client
                .call("/v3/kv/range", &range, Retry::Always)
                .await?;
            revision = reply.header.revision;
            for kv in &reply.kvs {
                let key = String::from_utf8_lossy(&kv.key.0).into_owned();
                let id = key[prefix.len()..].to_string();
                records.push((id, decode(&key, &kv.value.0)?));
            }
            match (reply.more, reply.kvs.last()) {
                (true, Some(last)) => {
                    from = last.key.0.clone();
                    from.push(0);
                }
                _ => return Ok(records),
            }
        }
    }
}

/// What a follower of a holon's journal read with [`journal_since`].
#[derive(Debug, Clone, Default, PartialEq, Eq)]
pub struct JournalRead {
    /// The records changed since the revision asked, oldest change first: (key under
    /// `<prefix>/journal/`, e.g. `order/o-1`, and its JSON).
    pub records: Vec<(String, Vec<u8>)>,
    /// Every change of the journal up to this revision is read (ask from here next).
    pub read_to: i64,
    /// The cluster's revision when etcd answered.
    pub revision: i64,
}

impl JournalRead {
    /// The revisions of the cluster not read yet (0 when caught up).
    pub fn lag(&self) -> u64 {
        u64::try_from(self.revision - self.read_to).unwrap_or(0)
    }
}

/// Reads at most `limit` records of `<prefix>/journal/` (a holon's [`FencedStore`])
/// changed after revision `after`, oldest change first, with one linearizable range
/// (`min_mod_revision`, sorted on the change's revision). A standby follows its
/// holder's journal with it: `read_to` is where to ask from next, and
/// [`JournalRead::lag`] how far it is behind the cluster. Deletions do not show (a
/// range sees only keys that exist): a follower that must know them re-reads.
///
/// `limit` must exceed the records one write may hold ([`MAX_RECORDS_PER_WRITE`]), so
/// that a page cut inside one revision still makes progress.
pub async fn journal_since(
    client: &Client,
    prefix: &str,
    after: i64,
    limit: usize,
) -> Result<JournalRead, EtcdError> {
    let journal = format!("{prefix}/journal/");
    let limit = limit.max(MAX_RECORDS_PER_WRITE + 1);
    let range = RangeRequest {
        key: journal.as_str().into(),
        range_end: Some(Base64(wire::prefix_end(journal.as_bytes()))),
        limit: i64::try_from(limit).unwrap_or(i64::MAX),
        min_mod_revision: after + 1,
        sort_order: Some("ASCEND"),
        sort_target: Some("MOD"),
        ..Default::default()
    };
    let reply: wire::RangeResponse = client.call("/v3/kv/range", &range, Retry::Always).await?;
    Ok(journal_read(&journal, after, reply))
}

/// The read a range reply of [`journal_since`] makes.
fn journal_read(journal: &str, after: i64, reply: wire::RangeResponse) -> JournalRead {
    let revision = reply.header.revision;
    let read_to = match (reply.more, reply.kvs.last()) {
        // Cut after a page: the last revision may have more keys beyond it, so it is
        // read only up to the one before (a write holds fewer keys than a page).
        (true, Some(last)) => (last.mod_revision - 1).max(after),
        _ => revision.max(after),
    };
    let records = reply
        .kvs
        .into_iter()
        .filter(|kv| kv.mod_revision <= read_to)
        .map(|kv| {
            let key = String::from_utf8_lossy(&kv.key.0);
            let key = key.strip_prefix(journal).unwrap_or(&key).to_string();
            (key, kv.value.0)
        })
        .collect();
    JournalRead {
        records,
        read_to,
        revision,
    }
}

/// A kind may not hold `/` (a list of one kind would see another's records); neither
/// may be empty.
fn check_names(kind: &str, id: &str) -> Result<(), EtcdError> {
    if kind.is_empty() || kind.contains('/') {
        return Err(EtcdError::BadName {
            what: "kind",
            name: kind.to_string(),
            why: "it must be non-empty and hold no '/'",
        });
    }
    if id.is_empty() {
        return Err(EtcdError::BadName {
            what: "id",
            name: id.to_string(),
            why: "it must be non-empty",
        });
    }
    Ok(())
}

fn decode<T: DeserializeOwned>(key: &str, body: &[u8]) -> Result<T, EtcdError> {
    serde_json::from_slice(body).map_err(|e| EtcdError::Decode {
        key: key.to_string(),
        why: e.to_string(),
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_journal_read_is_caught_up_unless_cut_after_a_page() {
        let reply = |more, revisions: &[i64]| {
            let text = format!(
                r#"{{"header":{{"revision":"20"}},"more":{more},"kvs":[{}]}}"#,
                revisions
                    .iter()
                    .map(|r| format!(
                        r#"{{"key":"cC9qb3VybmFsL28vMQ==","mod_revision":"{r}","value":"e30="}}"#
                    ))
                    .collect::<Vec<_>>()
                    .join(",")
            );
            serde_json::from_str::<wire::RangeResponse>(&text).unwrap()
        };
        let whole = journal_read("p/journal/", 10, reply(false, &[12, 15]));
        assert_eq!(
            (whole.read_to, whole.lag(), whole.records.len()),
            (20, 0, 2)
        );
        assert_eq!(whole.records[0], ("o/1".to_string(), b"{}".to_vec()));
        // Cut inside revision 15: read up to 14, the rest next time.
        let cut = journal_read("p/journal/", 10, reply(true, &[12, 15]));
        assert_eq!((cut.read_to, cut.lag(), cut.records.len()), (14, 6, 1));
        let nothing = journal_read("p/journal/", 20, reply(false, &[]));
        assert_eq!((nothing.read_to, nothing.lag()), (20, 0));
    }

    #[test]
    fn records_live_under_the_prefix_by_kind_and_id() {
        let client = Client::new(super::super::ClientConfig::new(["http://127.0.0.1:1"])).unwrap();
        let store = FencedStore::new(client, "holarchy/cell/order-node/orders", 7);
        assert_eq!(
            store.key("order", "o-12"),
            "holarchy/cell/order-node/orders/journal/order/o-12"
        );
        assert_eq!(store.epoch(), 7);
        assert!(check_names("order/x", "1").is_err());
        assert!(check_names("order", "").is_err());
        assert!(check_names("order", "a/b").is_ok());
    }

    #[tokio::test]
    async fn a_write_too_large_for_one_commit_is_refused_before_it_is_sent() {
        let client = Client::new(super::super::ClientConfig::new(["http://127.0.0.1:1"])).unwrap();
        let store = FencedStore::new(client, "p", 7);
        let ids: Vec<String> = (0..=MAX_RECORDS_PER_WRITE).map(|n| n.to_string()).collect();
        let error = store.delete("order", &ids).await.unwrap_err();
        assert!(
            matches!(error, EtcdError::TooLarge { count: 129, .. }),
            "{error}"
        );
    }
}
