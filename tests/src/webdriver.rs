//! A real browser for the tests: Debian's Chromium, headless, driven by its ChromeDriver
//! over the W3C WebDriver protocol (plain HTTP and JSON, so no client library).
//!
//! `.ci/run` installs both (`apt-get install chromium chromium-driver`). On a machine
//! without them [`Browser::start`] says why; a test then skips, unless
//! `HOLARCHY_REQUIRE_BROWSER` is set (CI sets it), so a missing browser never passes
//! there.

use std::io::{BufRead, Read, Write};
use std::net::TcpStream;
use std::path::Path;
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

use anyhow::{anyhow, bail, Context, Result};
use serde_json::{json, Value};

/// Where Debian puts them.
pub const CHROMIUM: &str = "/usr/bin/chromium";
pub const CHROMEDRIVER: &str = "/usr/bin/chromedriver";

/// The key under which WebDriver names an element.
const ELEMENT: &str = "element-6066-11e4-a52e-4f735466cecf";

/// Whether a browser test must run here: a browser is installed, or its absence is an
/// error (`HOLARCHY_REQUIRE_BROWSER`). `Err` says why the test is skipped.
pub fn browser_available() -> std::result::Result<(), String> {
    if Path::new(CHROMIUM).exists() && Path::new(CHROMEDRIVER).exists() {
        return Ok(());
    }
    let why = format!("no {CHROMIUM} or {CHROMEDRIVER} (apt-get install chromium chromium-driver)");
    if std::env::var_os("HOLARCHY_REQUIRE_BROWSER").is_some() {
        panic!("HOLARCHY_REQUIRE_BROWSER is set but there is {why}");
    }
    Err(why)
}

/// A headless Chromium session, closed (with its driver) when dropped.
pub struct Browser {
    driver: Child,
    address: String,
    session: String,
}

impl Browser {
    /// Starts ChromeDriver on a free port and a headless Chromium with a fresh profile in
    /// `profile`.
    pub fn start(profile: &Path) -> Result<Browser> {
        let port = crate::free_port();
        let driver = Command::new(CHROMEDRIVER)
            .arg(format!("--port={port}"))
            .stdout(Stdio::null())
            .stderr(Stdio::null())
            .spawn()
            .with_context(|| format!("start {CHROMEDRIVER}"))?;
        let mut browser = Browser {
            driver,
            address: format!("127.0.0.1:{port}"),
            session: String::new(),
        };
        let deadline = Instant::now() + Duration::from_secs(20);
        while browser.call("GET", "/status", None).is_err() {
            if Instant::now() >= deadline {
                bail!("chromedriver did not come up on {}", browser.address);
            }
            std::thread::sleep(Duration::from_millis(100));
        }
        // The flags a closed network needs (no background connections, no updates).
        let args = [
            "--headless",
            "--no-sandbox",
            "--disable-gpu",
            "--disable-quic",
            "--no-first-run",
            "--disable-background-networking",
            "--disable-component-update",
            "--disable-sync",
            "--window-size=1600,1000",
            &format!("--user-data-dir={}", profile.display()),
        ];
        let capabilities = json!({"capabilities": {"alwaysMatch": {
            "browserName": "chrome",
            // The dashboard's HTTPS certificate is issued by a test cell's own CA, which
            // this fresh profile does not know (the tests' own client checks the chain).
            "acceptInsecureCerts": true,
            "goog:chromeOptions": {"binary": CHROMIUM, "args": args}
        }}});
        let created = browser.call("POST", "/session", Some(capabilities))?;
        browser.session = created["sessionId"]
            .as_str()
            .ok_or_else(|| anyhow!("no session id in {created}"))?
            .to_string();
        Ok(browser)
    }

    /// One WebDriver command: its `value`, or the driver's error.
    fn call(&self, method: &str, path: &str, body: Option<Value>) -> Result<Value> {
        let body = body.map(|b| b.to_string()).unwrap_or_default();
        let mut stream = TcpStream::connect(&self.address)?;
        stream.set_read_timeout(Some(Duration::from_secs(60)))?;
        write!(
            stream,
            "{method} {path} HTTP/1.1\r\nHost: {}\r\nConnection: close\r\nContent-Type: application/json\r\nContent-Length: {}\r\n\r\n{body}",
            self.address,
            body.len()
        )?;
        // ChromeDriver keeps the connection open: read the head, then Content-Length bytes.
        let mut reader = std::io::BufReader::new(stream);
        let mut head = String::new();
        let mut length = 0usize;
        loop {
            let mut line = String::new();
            if reader.read_line(&mut line)? == 0 {
                bail!("{method} {path}: the driver closed the connection");
            }
            if line == "\r\n" {
                break;
            }
            if let Some((name, value)) = line.split_once(':') {
                if name.eq_ignore_ascii_case("content-length") {
                    length = value.trim().parse().context("Content-Length")?;
                }
            }
            head.push_str(&line);
        }
        let mut bytes = vec![0u8; length];
        reader.read_exact(&mut bytes)?;
        let body = String::from_utf8_lossy(&bytes);
        let value: Value =
            serde_json::from_str(&body).with_context(|| format!("{path}: {body}"))?;
        if !head.starts_with("HTTP/1.1 200") {
            bail!("{method} {path}: {}", value["value"]);
        }
        Ok(value["value"].clone())
    }

    fn session_call(&self, method: &str, path: &str, body: Option<Value>) -> Result<Value> {
        self.call(method, &format!("/session/{}{path}", self.session), body)
    }

    pub fn goto(&self, url: &str) -> Result<()> {
        self.session_call("POST", "/url", Some(json!({ "url": url })))?;
        Ok(())
    }

    /// Runs `script` (a function body) in the page; what it returns.
    pub fn execute(&self, script: &str) -> Result<Value> {
        self.session_call(
            "POST",
            "/execute/sync",
            Some(json!({ "script": script, "args": [] })),
        )
    }

    /// The element that `css` selects now, if any.
    pub fn find(&self, css: &str) -> Result<Option<String>> {
        let found = self.session_call(
            "POST",
            "/element",
            Some(json!({"using": "css selector", "value": css})),
        );
        match found {
            Ok(element) => Ok(element[ELEMENT].as_str().map(String::from)),
            Err(e) if e.to_string().contains("no such element") => Ok(None),
            Err(e) => Err(e),
        }
    }

    /// Waits until `css` selects an element (at most `within`): it, and how long it took.
    pub fn wait_for(&self, css: &str, within: Duration) -> Result<(String, Duration)> {
        let started = Instant::now();
        loop {
            if let Some(element) = self.find(css)? {
                return Ok((element, started.elapsed()));
            }
            if started.elapsed() >= within {
                bail!("nothing matched {css} within {within:?}");
            }
            std::thread::sleep(Duration::from_millis(50));
        }
    }

    pub fn text(&self, element: &str) -> Result<String> {
        let text = self.session_call("GET", &format!("/element/{element}/text"), None)?;
        Ok(text.as_str().unwrap_or_default().to_string())
    }

    pub fn click(&self, element: &str) -> Result<()> {
        self.session_call(
            "POST",
            &format!("/element/{element}/click"),
            Some(json!({})),
        )?;
        Ok(())
    }

    /// Replaces what an input holds with `text`.
    pub fn type_into(&self, element: &str, text: &str) -> Result<()> {
        self.session_call(
            "POST",
            &format!("/element/{element}/clear"),
            Some(json!({})),
        )?;
        self.session_call(
            "POST",
            &format!("/element/{element}/value"),
            Some(json!({ "text": text })),
        )?;
        Ok(())
    }

    /// Saves a PNG of the page to `path`.
    pub fn screenshot(&self, path: &Path) -> Result<()> {
        use base64::Engine;
        let encoded = self.session_call("GET", "/screenshot", None)?;
        let png = base64::engine::general_purpose::STANDARD
            .decode(encoded.as_str().unwrap_or_default())
            .context("the screenshot is not base64")?;
        std::fs::write(path, png).with_context(|| format!("write {}", path.display()))
    }
}

impl Drop for Browser {
    fn drop(&mut self) {
        if !self.session.is_empty() {
            if let Err(e) = self.session_call("DELETE", "", None) {
                eprintln!("cannot close the browser session: {e}");
            }
        }
        if let Err(e) = self.driver.kill() {
            eprintln!("cannot stop chromedriver: {e}");
        }
        if let Err(e) = self.driver.wait() {
            eprintln!("cannot reap chromedriver: {e}");
        }
    }
}
