//! What the plant's tests share: its control port's commands.

use tokio::io::{AsyncBufReadExt, AsyncWriteExt, BufReader};

/// One command on the plant's control port, and its answer as JSON.
pub async fn control(address: &str, line: &str) -> serde_json::Value {
    serde_json::from_str(&control_line(address, line).await).unwrap()
}

/// One command on the plant's control port, and its answer.
pub async fn control_line(address: &str, line: &str) -> String {
    let mut stream = tokio::net::TcpStream::connect(address).await.unwrap();
    stream
        .write_all(format!("{line}\n").as_bytes())
        .await
        .unwrap();
    let mut answer = String::new();
    BufReader::new(stream).read_line(&mut answer).await.unwrap();
    answer.trim_end().to_string()
}
