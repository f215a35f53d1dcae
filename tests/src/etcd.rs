//! A real etcd cluster for a test: members started from `/usr/bin/etcd` (Debian's
//! `etcd-server`) on loopback with free ports and their data in a temporary directory,
//! killed when the cluster is dropped. Its clients are served over plain HTTP, or over
//! mutual TLS ([`EtcdCluster::start_tls`]).

use std::path::PathBuf;
use std::process::{Command, Stdio};
use std::time::Duration;

use anyhow::{bail, Context, Result};
use holon::etcd::{Client, ClientConfig, TlsFiles};

use crate::*;

/// The etcd binary, if this machine has one (env `HOLARCHY_ETCD`, default
/// `/usr/bin/etcd`). `None` prints SKIPPED and the test skips, unless
/// `HOLARCHY_REQUIRE_ETCD` is set (CI sets it): then a missing etcd fails the test.
pub fn etcd_binary() -> Option<PathBuf> {
    let etcd = std::env::var_os("HOLARCHY_ETCD")
        .map(PathBuf::from)
        .unwrap_or_else(|| PathBuf::from("/usr/bin/etcd"));
    let works = Command::new(&etcd)
        .arg("--version")
        .stdout(Stdio::null())
        .stderr(Stdio::null())
        .status()
        .is_ok_and(|s| s.success());
    if works {
        return Some(etcd);
    }
    let why = format!(
        "no etcd at {} (apt-get install etcd-server, or set HOLARCHY_ETCD)",
        etcd.display()
    );
    if std::env::var_os("HOLARCHY_REQUIRE_ETCD").is_some() {
        panic!("HOLARCHY_REQUIRE_ETCD is set but {why}");
    }
    eprintln!("SKIPPED: {why}");
    None
}

/// One member of an [`EtcdCluster`].
pub struct EtcdMember {
    /// Its name in the cluster, `m0`, `m1`, ...
    pub name: String,
    /// Its client URL, `http://127.0.0.1:<port>` (`https://` with TLS).
    pub client_url: String,
    /// The process, `None` once killed.
    pub process: Option<Process>,
}

/// A cluster of etcd members on loopback, killed when dropped.
pub struct EtcdCluster {
    /// The members, in the order of their names.
    pub members: Vec<EtcdMember>,
    /// Data directories and logs (`<name>.stderr`).
    pub dir: tempfile::TempDir,
    /// With TLS: the files [`EtcdCluster::client`] connects with.
    pub client_tls: Option<TlsFiles>,
}

/// How the members of a cluster started with [`EtcdCluster::start_tls`] serve their
/// clients and each other: mutual TLS, every certificate checked against `trusted_ca`.
#[derive(Debug, Clone)]
pub struct MemberTls {
    /// Every member's certificate (`--cert-file`, `--peer-cert-file`): it must name
    /// 127.0.0.1 and serve as both server and client.
    pub certificate: PathBuf,
    /// Its key (`--key-file`).
    pub key: PathBuf,
    /// The CA a client's or a peer's certificate must be issued by (`--trusted-ca-file`
    /// with `--client-cert-auth`, `--peer-trusted-ca-file` with `--peer-client-cert-auth`).
    pub trusted_ca: PathBuf,
}

impl EtcdCluster {
    /// Starts `size` members of one new cluster with etcd's default timing (heartbeat
    /// 100 ms, election 1 s) and waits, at most [`WAIT`], until a put commits.
    pub async fn start(etcd: &std::path::Path, size: usize) -> Result<EtcdCluster> {
        Self::start_with(etcd, size, None).await
    }

    /// As [`EtcdCluster::start`], the members serving their clients and each other over
    /// mutual TLS with `members`' files, as docs/deploy.md runs them (the same
    /// certificate serves a member's client port and its peer links, where it is both
    /// server and client); [`EtcdCluster::client`] connects with `client`.
    pub async fn start_tls(
        etcd: &std::path::Path,
        size: usize,
        members: MemberTls,
        client: TlsFiles,
    ) -> Result<EtcdCluster> {
        Self::start_with(etcd, size, Some((members, client))).await
    }

    async fn start_with(
        etcd: &std::path::Path,
        size: usize,
        tls: Option<(MemberTls, TlsFiles)>,
    ) -> Result<EtcdCluster> {
        let dir = tempfile::tempdir()?;
        let scheme = if tls.is_some() { "https" } else { "http" };
        let ports: Vec<(u16, u16)> = (0..size).map(|_| (free_port(), free_port())).collect();
        let initial: Vec<String> = ports
            .iter()
            .enumerate()
            .map(|(n, (_, peer))| format!("m{n}={scheme}://127.0.0.1:{peer}"))
            .collect();
        let initial = initial.join(",");
        let mut members = Vec::new();
        for (n, (client, peer)) in ports.iter().enumerate() {
            let name = format!("m{n}");
            let client_url = format!("{scheme}://127.0.0.1:{client}");
            let mut tls_args: Vec<std::ffi::OsString> = Vec::new();
            if let Some((member, _)) = &tls {
                // The same files on the client port and on the peer links.
                for side in ["", "peer-"] {
                    for (flag, file) in [
                        ("cert-file", &member.certificate),
                        ("key-file", &member.key),
                        ("trusted-ca-file", &member.trusted_ca),
                    ] {
                        tls_args.push(format!("--{side}{flag}").into());
                        tls_args.push(file.clone().into());
                    }
                    tls_args.push(format!("--{side}client-cert-auth").into());
                }
            }
            let peer_url = format!("{scheme}://127.0.0.1:{peer}");
            let data = dir.path().join(&name);
            let stderr_path = dir.path().join(format!("{name}.stderr"));
            let child = Command::new(etcd)
                .args(["--name", &name, "--data-dir"])
                .arg(&data)
                .args([
                    "--listen-client-urls",
                    &client_url,
                    "--advertise-client-urls",
                    &client_url,
                    "--listen-peer-urls",
                    &peer_url,
                    "--initial-advertise-peer-urls",
                    &peer_url,
                    "--initial-cluster",
                    &initial,
                    "--initial-cluster-state",
                    "new",
                    "--initial-cluster-token",
                    &format!("holarchy-test-{}", std::process::id()),
                    "--logger",
                    "zap",
                    // As docs/deploy.md runs them: a member back from a partition
                    // does not depose the leader.
                    "--pre-vote",
                    // History compacted every 5 s (docs/deploy.md: 1 h): nothing of
                    // ours may read an old revision.
                    "--auto-compaction-mode",
                    "periodic",
                    "--auto-compaction-retention",
                    "5s",
                ])
                .args(&tls_args)
                .stdout(Stdio::null())
                .stderr(std::fs::File::create(&stderr_path)?)
                .spawn()
                .with_context(|| format!("start {}", etcd.display()))?;
            members.push(EtcdMember {
                name: name.clone(),
                client_url,
                process: Some(Process {
                    name: format!("etcd {name}"),
                    child: Some(child),
                    stderr_path,
                }),
            });
        }
        let cluster = EtcdCluster {
            members,
            dir,
            client_tls: tls.map(|(_, client)| client),
        };
        cluster.wait_ready().await?;
        Ok(cluster)
    }

    /// Waits until every member names the same raft leader.
    async fn wait_ready(&self) -> Result<()> {
        let deadline = tokio::time::Instant::now() + WAIT;
        let client = self.client();
        loop {
            let statuses = client.member_statuses().await;
            let leaders: Vec<u64> = statuses.iter().map(|s| s.leader_id).collect();
            if statuses.len() == self.members.len()
                && leaders[0] != 0
                && leaders.iter().all(|l| *l == leaders[0])
            {
                return Ok(());
            }
            if tokio::time::Instant::now() >= deadline {
                self.print_logs();
                bail!("the etcd cluster has no common leader after {WAIT:?}: {statuses:?}");
            }
            tokio::time::sleep(Duration::from_millis(100)).await;
        }
    }

    /// Every member's client URL, killed ones too (a client must cope with them).
    pub fn endpoints(&self) -> Vec<String> {
        self.members.iter().map(|m| m.client_url.clone()).collect()
    }

    /// A client of every member, with the default timeouts (and the cluster's client
    /// TLS files, with TLS).
    pub fn client(&self) -> Client {
        self.client_with(self.client_tls.clone())
            .expect("loopback endpoints")
    }

    /// A client of every member with these TLS files (`None`: plain HTTP).
    pub fn client_with(&self, tls: Option<TlsFiles>) -> Result<Client, holon::etcd::EtcdError> {
        Client::new(ClientConfig {
            tls,
            ..ClientConfig::new(self.endpoints())
        })
    }

    /// Kills member `n` (SIGKILL), as a host that dies.
    pub fn kill(&mut self, n: usize) {
        if let Some(mut process) = self.members[n].process.take() {
            process.kill();
        }
    }

    /// The index of the member that is the raft leader, as the live members say.
    pub async fn raft_leader(&self) -> Result<usize> {
        let statuses = self.client().member_statuses().await;
        let leader = statuses
            .iter()
            .find(|s| s.leader_id != 0 && s.member_id == s.leader_id)
            .with_context(|| format!("no member is the raft leader: {statuses:?}"))?;
        self.members
            .iter()
            .position(|m| m.client_url == leader.endpoint)
            .context("the leader is not a member")
    }

    /// Prints the end of each member's log (for a failed test).
    pub fn print_logs(&self) {
        for member in &self.members {
            let log =
                std::fs::read_to_string(self.dir.path().join(format!("{}.stderr", member.name)))
                    .unwrap_or_default();
            let tail: Vec<&str> = log.lines().rev().take(15).collect();
            eprintln!("--- etcd {} (last lines)", member.name);
            for line in tail.into_iter().rev() {
                eprintln!("{line}");
            }
        }
    }
}

/// An `etcd-holder` process (a test fixture) that holds a leader key, killed when
/// dropped.
pub struct EtcdHolder {
    /// The process.
    pub process: Process,
    /// The epoch it won.
    pub epoch: i64,
}

impl EtcdHolder {
    /// Starts `program` (the `etcd-holder` fixture: a test passes
    /// `env!("CARGO_BIN_EXE_etcd-holder")`) for `prefix` as `name` and waits, at most
    /// [`WAIT`], until it says it holds the key.
    pub fn start(
        program: &str,
        cluster: &EtcdCluster,
        prefix: &str,
        name: &str,
    ) -> Result<EtcdHolder> {
        use std::io::BufRead;
        let stderr_path = cluster.dir.path().join(format!("{name}.stderr"));
        let mut child = Command::new(program)
            .args([&cluster.endpoints().join(","), prefix, name])
            .stdout(Stdio::piped())
            .stderr(std::fs::File::create(&stderr_path)?)
            .spawn()
            .context("start etcd-holder")?;
        let stdout = child.stdout.take().context("its stdout")?;
        let process = Process {
            name: name.to_string(),
            child: Some(child),
            stderr_path,
        };
        let (lines, said) = std::sync::mpsc::channel();
        std::thread::spawn(move || {
            let mut first = String::new();
            let read = std::io::BufReader::new(stdout).read_line(&mut first);
            if lines.send(read.map(|_| first)).is_err() {
                eprintln!("etcd-holder's first line came after the test stopped waiting");
            }
        });
        let line = said.recv_timeout(WAIT).with_context(|| {
            format!(
                "etcd-holder did not win within {WAIT:?}: {}",
                process.stderr()
            )
        })??;
        let epoch = line
            .trim()
            .strip_prefix("epoch ")
            .and_then(|n| n.parse().ok())
            .with_context(|| format!("etcd-holder said {line:?}: {}", process.stderr()))?;
        Ok(EtcdHolder { process, epoch })
    }
}
