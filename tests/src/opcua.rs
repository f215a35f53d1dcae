//! The OPC UA tests' client: the foreign client (Python asyncua, tests/opcua/driver.py)
//! driven one command at a time.

use std::path::Path;
use std::process::Stdio;
use std::time::Duration;

use serde_json::Value;
use tokio::io::{AsyncBufReadExt, AsyncWriteExt, BufReader, Lines};
use tokio::process::{Child, ChildStdin, ChildStdout};

use crate::workspace_root;

/// The driver script, connected to a server.
pub struct Driver {
    /// The Python process (killed when dropped).
    child: Child,
    /// Where the commands go.
    stdin: ChildStdin,
    /// Its answers, one JSON line each.
    lines: Lines<BufReader<ChildStdout>>,
}

impl Driver {
    /// Starts the driver on `url` and returns it with its first line
    /// (`{"connected": ...}`).
    pub async fn start(python: &Path, url: &str, cell: &str, extra: &[&str]) -> (Driver, Value) {
        let script = workspace_root().join("tests/opcua/driver.py");
        let mut child = tokio::process::Command::new(python)
            .arg(script)
            .args([url, cell])
            .args(extra)
            .stdin(Stdio::piped())
            .stdout(Stdio::piped())
            .kill_on_drop(true)
            .spawn()
            .expect("start the OPC UA driver");
        let stdin = child.stdin.take().unwrap();
        let lines = BufReader::new(child.stdout.take().unwrap()).lines();
        let mut driver = Driver {
            child,
            stdin,
            lines,
        };
        let first = driver.line().await;
        (driver, first)
    }

    pub async fn line(&mut self) -> Value {
        let line = tokio::time::timeout(Duration::from_secs(30), self.lines.next_line())
            .await
            .expect("the driver answers within 30 s")
            .expect("the driver's stdout")
            .expect("the driver still runs (see its stderr above)");
        serde_json::from_str(&line).unwrap_or_else(|e| panic!("{e}: {line}"))
    }

    pub async fn ask(&mut self, command: &str) -> Value {
        self.stdin
            .write_all(format!("{command}\n").as_bytes())
            .await
            .expect("write to the driver");
        self.stdin.flush().await.unwrap();
        self.line().await
    }

    /// The status of a method call.
    pub async fn call(&mut self, command: &str) -> String {
        let answer = self.ask(command).await;
        answer["status"].as_str().unwrap_or_default().to_string()
    }

    /// Reads until `value` is read, at most 5 s (the value is pushed from the resource's
    /// state publication).
    pub async fn wait_read(&mut self, what: &str, value: Value) {
        let deadline = tokio::time::Instant::now() + Duration::from_secs(5);
        loop {
            let read = self.ask(&format!("read {what}")).await;
            if read["value"] == value {
                return;
            }
            assert!(
                tokio::time::Instant::now() < deadline,
                "{what}: never {value}, last {read}"
            );
            tokio::time::sleep(Duration::from_millis(50)).await;
        }
    }

    pub async fn resources(&mut self) -> Vec<String> {
        let answer = self.ask("browse").await;
        serde_json::from_value(answer["resources"].clone())
            .unwrap_or_else(|e| panic!("browse: {e}: {answer}"))
    }

    pub async fn quit(mut self) {
        let _ = self.stdin.write_all(b"quit\n").await;
        let _ = tokio::time::timeout(Duration::from_secs(10), self.child.wait()).await;
    }
}
