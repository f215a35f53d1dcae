//! A test fixture: a process that campaigns for an etcd leader key and, once it holds
//! it, prints `epoch <N>` and holds it (renewing its lease) until it is killed. The etcd
//! store's tests kill it (SIGKILL) to see its standby take over when the lease expires.
//!
//! Usage: `etcd-holder ENDPOINTS PREFIX NAME` (ENDPOINTS comma-separated).

use std::io::Write;

use holon::etcd::{Candidate, Client, ClientConfig, ElectionConfig};

#[tokio::main]
async fn main() -> anyhow::Result<()> {
    let args: Vec<String> = std::env::args().skip(1).collect();
    let [endpoints, prefix, name] = args.as_slice() else {
        anyhow::bail!("usage: etcd-holder ENDPOINTS PREFIX NAME");
    };
    let client = Client::new(ClientConfig::new(endpoints.split(',')))?;
    let candidate = Candidate::new(client, ElectionConfig::new(prefix.as_str(), name.as_str()));
    let Some(leader) = candidate.campaign(std::future::pending()).await? else {
        anyhow::bail!("the campaign ended without a win");
    };
    let mut out = std::io::stdout();
    writeln!(out, "epoch {}", leader.epoch())?;
    out.flush()?;
    let why = leader.deposed().await;
    anyhow::bail!("deposed: {why}")
}
