//! The TLS section: booking over mutual TLS with access control against plain TCP.

use std::time::{Duration, Instant};

use anyhow::{anyhow, bail, Result};
use holarchy_tests::{free_port, resource_config, Cell};
use schemas::CellKeys;
use serde_json::json;

use crate::booking::book_and_cancel;
use crate::run::Run;
use crate::stats::Latency;

/// Booking over mutual TLS with access control against plain TCP, in the same run: a
/// second cell (`cell certs` identities, a TLS router in this process, `robot7` with
/// `--pki`) beside the plain one, one TLS booking and one TCP booking in turn.
pub async fn section(run: &mut Run) -> Result<()> {
    let dir = run.dir.join("tls");
    std::fs::create_dir_all(&dir)?;
    let endpoint = format!("tls/127.0.0.1:{}", free_port());
    std::fs::write(
        dir.join("cell.toml"),
        format!(
            "cell = \"bench\"\n[router]\nlisten = [\"{endpoint}\"]\n[[process]]\nname = \"robot7\"\nprogram = \"holon-node\"\nidentity = \"resource.robot7\"\n"
        ),
    )?;
    let certs = std::process::Command::new(holarchy_tests::bin("cell"))
        .arg("certs")
        .arg(&dir)
        .output()?;
    if !certs.status.success() {
        bail!("cell certs: {}", String::from_utf8_lossy(&certs.stderr));
    }
    let pki = dir.join("pki");
    let settings = holon::ZenohSettings {
        mode: holon::Mode::Router,
        listen: vec![endpoint.clone()],
        tls: Some(holon::tls::TlsSettings {
            pki: Some(pki.clone()),
            ..Default::default()
        }),
        ..Default::default()
    };
    let session = settings
        .open("router.local", Duration::from_secs(10))
        .await
        .map_err(|e| anyhow!("{e}"))?;
    let tls_cell = Cell {
        session,
        keys: CellKeys::new("bench")?,
        endpoint: endpoint.clone(),
    };
    let config = resource_config(&run.dir, "robot7", 5000)?;
    let mut robot7 = std::process::Command::new(holarchy_tests::bin("holon-node"))
        .arg("--config")
        .arg(&config)
        .args(["--cell", "bench", "--connect", &endpoint])
        .args(["--controller", &run.sim.address])
        .arg("--pki")
        .arg(&pki)
        .arg("--data-dir")
        .arg(dir.join("data"))
        .env("RUST_LOG", holarchy_tests::holon_log_level())
        .stdout(std::process::Stdio::null())
        .stderr(std::fs::File::create(dir.join("robot7.stderr"))?)
        .spawn()?;
    let ready = tls_cell
        .wait_state("robot7", "free", |s| s["state"] == "free")
        .await;
    if let Err(e) = ready {
        let _ = robot7.kill();
        bail!("robot7 (TLS) did not come up: {e}");
    }
    let (mut tls_times, mut tcp_times) = (Vec::new(), Vec::new());
    let started = Instant::now();
    for i in 0..run.samples + 100 {
        for (cell, resource, times) in [
            (&tls_cell, "robot7", &mut tls_times),
            (&run.cell, "robot1", &mut tcp_times),
        ] {
            let (booked, _) = book_and_cancel(cell, resource, &format!("tls/{i}/1")).await?;
            if i >= 100 {
                times.push(booked);
            }
        }
    }
    let total = started.elapsed();
    let _ = robot7.kill();
    let _ = robot7.wait();
    let tls = Latency::new(tls_times, total);
    let tcp = Latency::new(tcp_times, total);
    run.table.add(
        "booking round trip over mutual TLS + access control (power_loss)",
        tls.p50_p99(),
        format!(
            "{:.2}x plain TCP interleaved (p50 {:.0} us, p99 {:.0} us)",
            tls.pct(0.5) / tcp.pct(0.5),
            tcp.pct(0.5),
            tcp.pct(0.99)
        ),
        json!({"tls": tls.json(), "tcp": tcp.json(), "ratio_p50": tls.pct(0.5) / tcp.pct(0.5)}),
    );
    if let Err(e) = tls_cell.session.close().await {
        eprintln!("closing the TLS router: {e}");
    }
    Ok(())
}
