//! The control socket of `cell up` (`DIR/run/<host>.sock`): each connection of
//! `cell upgrade` carries one upgrade request to the supervisor and its outcome back.

use std::path::{Path, PathBuf};
use std::time::Duration;

use anyhow::{Context, Result};
use tokio::sync::{mpsc, oneshot};

use crate::up::upgrade::{UpgradeOutcome, UpgradeRequest};

/// An upgrade asked on the control socket, and where its outcome goes.
pub(super) type Upgrade = (UpgradeRequest, oneshot::Sender<UpgradeOutcome>);

/// The control socket `cell upgrade` talks to; removed when dropped.
pub(super) struct Control {
    path: PathBuf,
    accept: tokio::task::JoinHandle<()>,
}

impl Control {
    /// Listens on `DIR/run/<host>.sock` (only this user may connect): each connection
    /// carries one upgrade request, answered with its outcome.
    pub(super) fn listen(dir: &Path, host: &str) -> Result<(Control, mpsc::Receiver<Upgrade>)> {
        use std::os::unix::fs::PermissionsExt;
        let path = crate::up::upgrade::socket_path(dir, host);
        let run = path.parent().expect("the socket is in DIR/run");
        std::fs::create_dir_all(run)?;
        std::fs::set_permissions(run, std::fs::Permissions::from_mode(0o700))?;
        if path.exists() {
            if std::os::unix::net::UnixStream::connect(&path).is_ok() {
                anyhow::bail!(
                    "another cell up for host {host} runs here ({} answers)",
                    path.display()
                );
            }
            // Left by a cell up that was killed.
            std::fs::remove_file(&path)?;
        }
        let listener = tokio::net::UnixListener::bind(&path)
            .with_context(|| format!("cannot listen on {}", path.display()))?;
        std::fs::set_permissions(&path, std::fs::Permissions::from_mode(0o600))?;
        let (sender, upgrades) = mpsc::channel(4);
        let accept = tokio::spawn(async move {
            loop {
                match listener.accept().await {
                    Ok((stream, _)) => {
                        tokio::spawn(serve_control(stream, sender.clone()));
                    }
                    Err(e) => {
                        tracing::warn!(error = %e, "the control socket failed; cell upgrade is unavailable");
                        return;
                    }
                }
            }
        });
        Ok((Control { path, accept }, upgrades))
    }
}

impl Drop for Control {
    fn drop(&mut self) {
        self.accept.abort();
        if let Err(e) = std::fs::remove_file(&self.path) {
            tracing::warn!(path = %self.path.display(), error = %e, "cannot remove the control socket");
        }
    }
}

/// One `cell upgrade` connection: its request to the supervisor, the outcome back.
async fn serve_control(stream: tokio::net::UnixStream, upgrades: mpsc::Sender<Upgrade>) {
    use tokio::io::{AsyncBufReadExt, AsyncWriteExt, BufReader};
    let (read, mut write) = stream.into_split();
    let mut line = String::new();
    let outcome = match tokio::time::timeout(
        Duration::from_secs(10),
        BufReader::new(read).read_line(&mut line),
    )
    .await
    {
        Ok(Ok(_)) => match serde_json::from_str::<UpgradeRequest>(line.trim()) {
            Ok(request) => {
                let (reply, outcome) = oneshot::channel();
                if upgrades.send((request, reply)).await.is_err() {
                    failed("cell up is stopping")
                } else {
                    outcome
                        .await
                        .unwrap_or_else(|_| failed("cell up stopped before the upgrade ended"))
                }
            }
            Err(e) => failed(&format!("not an upgrade request: {e}")),
        },
        Ok(Err(e)) => failed(&format!("cannot read the request: {e}")),
        Err(_) => failed("no request within 10 s"),
    };
    let mut answer = serde_json::to_vec(&outcome).expect("an outcome serializes");
    answer.push(b'\n');
    if let Err(e) = write.write_all(&answer).await {
        tracing::warn!(error = %e, ok = outcome.ok, "cannot tell cell upgrade how the upgrade went");
    }
}

/// An outcome that tells `cell upgrade` its upgrade failed, and why.
pub(super) fn failed(message: &str) -> UpgradeOutcome {
    UpgradeOutcome {
        ok: false,
        message: message.to_string(),
    }
}
