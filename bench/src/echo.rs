//! The echo helpers this binary runs as child processes (a TCP echo server, a zenoh
//! queryable that answers with the payload), the floors' other end.

use std::process::{Child, Command, Stdio};
use std::time::Duration;

use anyhow::{anyhow, Result};
use tokio::io::{AsyncReadExt, AsyncWriteExt};

/// The echo helper's key: a queryable that answers with the query's payload.
pub const ECHO_KEY: &str = "holarchy/bench/echo";

pub async fn echo_tcp(listen: &str) -> Result<()> {
    let listener = tokio::net::TcpListener::bind(listen).await?;
    println!("listening on {}", listener.local_addr()?);
    loop {
        let (mut socket, _) = listener.accept().await?;
        socket.set_nodelay(true)?;
        tokio::spawn(async move {
            let mut buf = vec![0u8; 65536];
            while let Ok(n) = socket.read(&mut buf).await {
                if n == 0 || socket.write_all(&buf[..n]).await.is_err() {
                    break;
                }
            }
        });
    }
}

pub async fn echo_zenoh(connect: &str, key: &str) -> Result<()> {
    let settings = holon::ZenohSettings {
        mode: holon::Mode::Peer,
        connect: vec![connect.to_string()],
        listen: vec!["tcp/127.0.0.1:0".into()],
        ..Default::default()
    };
    let session = settings
        .open("router.local", Duration::from_secs(10))
        .await
        .map_err(|e| anyhow!("{e}"))?;
    let queryable = session
        .declare_queryable(key)
        .await
        .map_err(|e| anyhow!("{e}"))?;
    let _token = session
        .liveliness()
        .declare_token(format!("{key}/alive"))
        .await
        .map_err(|e| anyhow!("{e}"))?;
    println!("ready");
    while let Ok(query) = queryable.recv_async().await {
        let payload = query
            .payload()
            .map(|p| p.to_bytes().into_owned())
            .unwrap_or_default();
        let _ = query.reply(query.key_expr().clone(), payload).await;
    }
    Ok(())
}

pub fn spawn_helper(args: &[&str]) -> Result<(Child, String)> {
    use std::io::BufRead;
    let mut child = Command::new(std::env::current_exe()?)
        .args(args)
        .stdout(Stdio::piped())
        .stderr(Stdio::null())
        .spawn()?;
    let mut line = String::new();
    std::io::BufReader::new(child.stdout.take().expect("piped")).read_line(&mut line)?;
    Ok((child, line.trim().to_string()))
}
