use super::*;

#[derive(Debug, PartialEq, Serialize, Deserialize)]
struct Record {
    n: u32,
    text: String,
}

#[test]
fn the_journal_is_its_owners_alone() {
    use std::os::unix::fs::PermissionsExt;
    let dir = tempfile::tempdir().unwrap();
    let mode = |name: &str| {
        std::fs::metadata(dir.path().join(name))
            .unwrap()
            .permissions()
            .mode()
            & 0o777
    };
    {
        let journal = Journal::open(dir.path(), "j.sqlite", Durability::PowerLoss).unwrap();
        journal
            .put(
                "order",
                "a",
                &Record {
                    n: 1,
                    text: "x".into(),
                },
            )
            .unwrap();
        // SQLite gives the WAL the database file's mode (no -shm: exclusive locking).
        for name in ["j.sqlite", "j.sqlite-wal"] {
            assert_eq!(mode(name), 0o600, "{name}");
        }
    }
    std::fs::set_permissions(
        dir.path().join("j.sqlite"),
        std::fs::Permissions::from_mode(0o644),
    )
    .unwrap();
    drop(Journal::open(dir.path(), "j.sqlite", Durability::PowerLoss).unwrap());
    assert_eq!(mode("j.sqlite"), 0o600, "narrowed when reopened");
}

#[test]
fn records_survive_reopening() {
    let dir = tempfile::tempdir().unwrap();
    {
        let journal = Journal::open(dir.path(), "j.sqlite", Durability::PowerLoss).unwrap();
        journal
            .put(
                "order",
                "a",
                &Record {
                    n: 1,
                    text: "x".into(),
                },
            )
            .unwrap();
        journal
            .put(
                "order",
                "b",
                &Record {
                    n: 2,
                    text: "y".into(),
                },
            )
            .unwrap();
        journal
            .put(
                "order",
                "a",
                &Record {
                    n: 3,
                    text: "z".into(),
                },
            )
            .unwrap();
        journal.put("meta", "seq", &7u64).unwrap();
        journal.delete("order", ["b", "missing"]).unwrap();
    }
    let journal = Journal::open(dir.path(), "j.sqlite", Durability::ProcessCrash).unwrap();
    let orders: Vec<(String, Record)> = journal.list("order").unwrap();
    assert_eq!(
        orders,
        vec![(
            "a".to_string(),
            Record {
                n: 3,
                text: "z".into()
            }
        )]
    );
    assert_eq!(journal.get::<u64>("meta", "seq").unwrap(), Some(7));
    assert_eq!(journal.get::<u64>("meta", "other").unwrap(), None);
}

#[test]
fn several_records_are_read_in_the_order_asked() {
    let dir = tempfile::tempdir().unwrap();
    let journal = Journal::open(dir.path(), "j.sqlite", Durability::PowerLoss).unwrap();
    for (id, n) in [("a", 1u32), ("b", 2), ("c", 3)] {
        journal.put("order", id, &n).unwrap();
    }
    journal.put("meta", "b", &9u32).unwrap();
    let read: Vec<(String, u32)> = journal.get_many("order", ["c", "missing", "b"]).unwrap();
    assert_eq!(read, vec![("c".to_string(), 3), ("b".to_string(), 2)]);
    let none: Vec<(String, u32)> = journal.get_many("order", Vec::<String>::new()).unwrap();
    assert!(none.is_empty());
    let mut visited = Vec::new();
    journal
        .for_each("order", |id, n: u32| visited.push((id, n)))
        .unwrap();
    assert_eq!(visited, journal.list::<u32>("order").unwrap());
}

#[test]
fn a_batch_is_written_in_one_commit_or_not_at_all() {
    let dir = tempfile::tempdir().unwrap();
    let journal = Journal::open(dir.path(), "j.sqlite", Durability::PowerLoss).unwrap();
    let (one, two) = (serde_json::json!(1), serde_json::json!({"n": 2}));
    journal
        .put_all([("meta", "next", &one), ("order", "b", &two)])
        .unwrap();
    assert_eq!(journal.get::<u64>("meta", "next").unwrap(), Some(1));
    assert_eq!(
        journal.get::<serde_json::Value>("order", "b").unwrap(),
        Some(two.clone())
    );
    // A batch that fails half-way (here: a trigger refuses its second record)
    // leaves nothing of itself.
    journal
        .connection()
        .execute_batch("CREATE TRIGGER no_c BEFORE INSERT ON records WHEN NEW.id = 'c' BEGIN SELECT RAISE(ABORT, 'refused'); END;")
        .unwrap();
    let three = serde_json::json!(3);
    assert!(journal
        .put_all([("order", "a", &three), ("order", "c", &three)])
        .is_err());
    assert_eq!(
        journal.get::<serde_json::Value>("order", "a").unwrap(),
        None
    );
}

/// Writers that queue while the connection is taken (here: held by the test) share
/// the next commit; each returns only once its record is committed.
#[test]
fn writers_at_the_same_time_share_one_commit() {
    let dir = tempfile::tempdir().unwrap();
    let journal =
        std::sync::Arc::new(Journal::open(dir.path(), "j.sqlite", Durability::PowerLoss).unwrap());
    let held = journal.connection();
    let writers: Vec<_> = (0..4)
        .map(|n| {
            let journal = journal.clone();
            std::thread::spawn(move || journal.put("order", &format!("o{n}"), &n))
        })
        .collect();
    while journal.queue().records.len() < 4 {
        std::thread::sleep(std::time::Duration::from_millis(1));
    }
    assert_eq!(
        journal.commits(),
        0,
        "nobody committed while the connection was held"
    );
    drop(held);
    for writer in writers {
        writer.join().unwrap().unwrap();
    }
    assert_eq!(journal.commits(), 1, "four records, one commit");
    let records: Vec<(String, u32)> = journal.list("order").unwrap();
    assert_eq!(records.len(), 4);
    // A lone writer commits alone.
    journal.put("order", "o9", &9u32).unwrap();
    assert_eq!(journal.commits(), 2);
}

/// A shared commit that fails fails every writer in it, and writes none of them.
#[test]
fn a_shared_commit_that_fails_fails_all_its_writers() {
    let dir = tempfile::tempdir().unwrap();
    let journal =
        std::sync::Arc::new(Journal::open(dir.path(), "j.sqlite", Durability::PowerLoss).unwrap());
    journal
        .connection()
        .execute_batch("CREATE TRIGGER no_c BEFORE INSERT ON records WHEN NEW.id = 'c' BEGIN SELECT RAISE(ABORT, 'refused'); END;")
        .unwrap();
    let held = journal.connection();
    let writers: Vec<_> = ["a", "b", "c"]
        .into_iter()
        .map(|id| {
            let journal = journal.clone();
            std::thread::spawn(move || journal.put("order", id, &1u32))
        })
        .collect();
    while journal.queue().records.len() < 3 {
        std::thread::sleep(std::time::Duration::from_millis(1));
    }
    drop(held);
    for writer in writers {
        let refused = writer.join().unwrap().unwrap_err();
        assert!(refused.to_string().contains("refused"), "{refused}");
    }
    assert!(journal.list::<u32>("order").unwrap().is_empty());
    assert!(journal.queue().failed.is_empty(), "every writer was told");
    // The journal goes on.
    journal.put("order", "d", &2u32).unwrap();
    assert_eq!(journal.get::<u32>("order", "d").unwrap(), Some(2));
}

#[test]
fn a_second_opener_is_refused() {
    let dir = tempfile::tempdir().unwrap();
    let _first = Journal::open(dir.path(), "j.sqlite", Durability::PowerLoss).unwrap();
    let second = Journal::open(dir.path(), "j.sqlite", Durability::PowerLoss).unwrap_err();
    assert!(matches!(second, JournalError::InUse { .. }), "{second}");
}

#[test]
fn a_successor_opens_the_journal_once_its_holder_closes_it() {
    let dir = tempfile::tempdir().unwrap();
    let first = Journal::open(dir.path(), "j.sqlite", Durability::PowerLoss).unwrap();
    first.put("order", "a", &1u32).unwrap();
    // Still held after the patience: refused, as a twin would be.
    let refused = Journal::open_when_free(
        dir.path(),
        "j.sqlite",
        Durability::PowerLoss,
        std::time::Duration::from_millis(100),
    )
    .unwrap_err();
    assert!(matches!(refused, JournalError::InUse { .. }), "{refused}");
    let closer = std::thread::spawn(move || {
        std::thread::sleep(std::time::Duration::from_millis(200));
        drop(first);
    });
    let second = Journal::open_when_free(
        dir.path(),
        "j.sqlite",
        Durability::PowerLoss,
        std::time::Duration::from_secs(10),
    )
    .unwrap();
    assert_eq!(second.get::<u32>("order", "a").unwrap(), Some(1));
    closer.join().unwrap();
}

#[test]
fn a_record_that_does_not_decode_is_a_clear_error() {
    let dir = tempfile::tempdir().unwrap();
    let journal = Journal::open(dir.path(), "j.sqlite", Durability::PowerLoss).unwrap();
    journal.put("order", "a", &"text").unwrap();
    let err = journal.get::<Record>("order", "a").unwrap_err().to_string();
    assert!(err.contains("order/a"), "{err}");
}

#[test]
fn durability_names_parse() {
    assert_eq!(
        "power_loss".parse::<Durability>().unwrap(),
        Durability::PowerLoss
    );
    assert_eq!(
        "process_crash".parse::<Durability>().unwrap(),
        Durability::ProcessCrash
    );
    assert!("sometimes".parse::<Durability>().is_err());
}

fn journal_with_records(dir: &Path) {
    let journal = Journal::open(dir, "j.sqlite", Durability::PowerLoss).unwrap();
    for n in 0..50 {
        journal
            .put(
                "order",
                &n.to_string(),
                &Record {
                    n,
                    text: "x".repeat(200),
                },
            )
            .unwrap();
    }
}

fn assert_damaged(result: Result<Journal, JournalError>, what: &str) {
    match result {
        Err(e @ JournalError::Damaged { .. }) => {
            let text = e.to_string();
            assert!(text.contains("not replaced by an empty"), "{text}");
        }
        Err(other) => panic!("{what}: expected Damaged, got {other}"),
        Ok(_) => panic!("{what}: a damaged journal was opened"),
    }
}

#[test]
fn a_zero_length_journal_is_refused_not_made_empty() {
    let dir = tempfile::tempdir().unwrap();
    journal_with_records(dir.path());
    std::fs::write(dir.path().join("j.sqlite"), b"").unwrap();
    assert_damaged(
        Journal::open(dir.path(), "j.sqlite", Durability::PowerLoss),
        "zero length",
    );
    assert_eq!(
        std::fs::metadata(dir.path().join("j.sqlite"))
            .unwrap()
            .len(),
        0,
        "the file is left as it was"
    );
}

#[test]
fn a_garbage_wal_is_refused() {
    let dir = tempfile::tempdir().unwrap();
    journal_with_records(dir.path());
    std::fs::write(dir.path().join("j.sqlite-wal"), vec![0x5a; 4096]).unwrap();
    assert_damaged(
        Journal::open(dir.path(), "j.sqlite", Durability::PowerLoss),
        "garbage WAL",
    );
}

#[test]
fn damaged_pages_are_refused_at_open() {
    let dir = tempfile::tempdir().unwrap();
    journal_with_records(dir.path());
    let path = dir.path().join("j.sqlite");
    let mut bytes = std::fs::read(&path).unwrap();
    assert!(bytes.len() > 8192, "{}", bytes.len());
    // Scribble over the second page (the table's first page), keep the header.
    for b in &mut bytes[4096..6000] {
        *b = 0xa5;
    }
    std::fs::write(&path, bytes).unwrap();
    assert_damaged(
        Journal::open(dir.path(), "j.sqlite", Durability::PowerLoss),
        "damaged page",
    );
}

#[test]
fn a_read_only_data_directory_is_named() {
    let dir = tempfile::tempdir().unwrap();
    let data = dir.path().join("data");
    std::fs::create_dir(&data).unwrap();
    use std::os::unix::fs::PermissionsExt;
    std::fs::set_permissions(&data, std::fs::Permissions::from_mode(0o555)).unwrap();
    if std::fs::write(data.join("probe"), b"").is_ok() {
        // Running as root: permissions do not stop writes; nothing to test here.
        return;
    }
    let error = Journal::open(&data, "j.sqlite", Durability::PowerLoss)
        .unwrap_err()
        .to_string();
    assert!(error.contains("is not writable"), "{error}");
}
