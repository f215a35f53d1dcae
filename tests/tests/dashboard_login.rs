//! People log in to a secure cell's dashboard: HTTPS, users and roles from the cell's
//! users file (`cell users`), client certificates of the cell CA, sessions that end,
//! failed logins slowed and locked out, and an audit trail of who did what.

use std::io::{BufRead, BufReader};
use std::os::unix::fs::PermissionsExt;
use std::path::Path;
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

use holarchy_tests::secure_cell::{add_user, secure_cell, SecureCell};
use holarchy_tests::web::Web;
use holarchy_tests::{bin, webdriver, WAIT};

/// A `cell dashboard` process of a secure cell, and its address.
struct Dashboard {
    child: Child,
    /// `127.0.0.1:PORT`.
    address: String,
}

impl Dashboard {
    /// `cell dashboard` of `cell`, on a port of its choosing, joined as `identity`.
    fn command(cell: &SecureCell, identity: &str) -> Command {
        let pki = cell.pki().display().to_string();
        let mut command = Command::new(bin("cell"));
        command
            .args([
                "dashboard",
                "--cell",
                cell.keys.cell(),
                "--connect",
                &cell.endpoint,
            ])
            .args([
                "--listen",
                "127.0.0.1:0",
                "--pki",
                &pki,
                "--identity",
                identity,
            ]);
        command
    }

    /// A dashboard of `cell` joined as `identity`, with `extra` flags; waits for the
    /// line that says where it serves, which must be `scheme`.
    fn start(cell: &SecureCell, identity: &str, scheme: &str, extra: &[&str]) -> Dashboard {
        let mut child = Dashboard::command(cell, identity)
            .args(extra)
            .stdout(Stdio::piped())
            .stderr(Stdio::inherit())
            .spawn()
            .unwrap();
        let mut line = String::new();
        BufReader::new(child.stdout.take().unwrap())
            .read_line(&mut line)
            .unwrap();
        // "dashboard of cell C on https://127.0.0.1:PORT/"
        let prefix = format!("{scheme}://");
        let address = line
            .trim()
            .rsplit(prefix.as_str())
            .next()
            .unwrap()
            .trim_end_matches('/')
            .to_string();
        assert!(address.starts_with("127.0.0.1:"), "{line}");
        Dashboard { child, address }
    }

    /// An HTTPS client of it that trusts the cell CA, with `identity`'s client
    /// certificate when given.
    fn web(&self, cell: &SecureCell, identity: Option<&str>) -> Web {
        let pki = cell.pki();
        let cert = identity.map(|i| (pki.join(format!("{i}.pem")), pki.join(format!("{i}.key"))));
        Web::https(
            &self.address,
            &pki.join("ca.pem"),
            cert.as_ref().map(|(c, k)| (c.as_path(), k.as_path())),
        )
        .unwrap()
    }

    fn url(&self, path: &str) -> String {
        format!("https://{}{path}", self.address)
    }
}

impl Drop for Dashboard {
    fn drop(&mut self) {
        if let Err(e) = self.child.kill() {
            eprintln!("cannot stop the dashboard: {e}");
        }
        if let Err(e) = self.child.wait() {
            eprintln!("cannot reap the dashboard: {e}");
        }
    }
}

fn mode(path: &Path) -> u32 {
    std::fs::metadata(path).unwrap().permissions().mode() & 0o777
}

/// Waits until `check` holds on `GET path` (JSON) as `web` sees it.
fn wait_json(web: &Web, path: &str, what: &str, check: impl Fn(&serde_json::Value) -> bool) {
    let started = Instant::now();
    loop {
        let answer = web.call("GET", path, "");
        if answer.status == 200 && check(&answer.json()) {
            return;
        }
        assert!(
            started.elapsed() < WAIT,
            "{what} never showed on {path}: {answer:?}"
        );
        std::thread::sleep(Duration::from_millis(100));
    }
}

/// The pid of the holon-node process that runs resource `name` of cell `cell`.
fn resource_pid(cell: &str, name: &str) -> Option<i32> {
    std::fs::read_dir("/proc")
        .ok()?
        .flatten()
        .find_map(|entry| {
            let pid: i32 = entry.file_name().to_str()?.parse().ok()?;
            let cmdline = std::fs::read(entry.path().join("cmdline")).ok()?;
            let args: Vec<&[u8]> = cmdline.split(|b| *b == 0).collect();
            let has = |flag: &str, value: &str| {
                args.windows(2)
                    .any(|w| w[0] == flag.as_bytes() && w[1] == value.as_bytes())
            };
            let holon_node = args.first().is_some_and(|a| a.ends_with(b"holon-node"));
            (holon_node && has("--cell", cell) && has("--name", name)).then_some(pid)
        })
}

/// Logs in on the login page the browser shows.
fn log_in(browser: &webdriver::Browser, name: &str, password: &str, within: Duration) {
    browser.wait_for("#login", within).unwrap();
    let (field, _) = browser.wait_for("#name", within).unwrap();
    browser.type_into(&field, name).unwrap();
    let (field, _) = browser.wait_for("#password", within).unwrap();
    browser.type_into(&field, password).unwrap();
    let (button, _) = browser.wait_for("#login-button", within).unwrap();
    browser.click(&button).unwrap();
}

/// What `fetch` of `path` with `init` (a JS object) answers in the page: the status.
fn fetch_status(browser: &webdriver::Browser, path: &str, init: &str) -> i64 {
    browser
        .execute(&format!(
            "return fetch({path:?}, {init}).then((r) => r.status);"
        ))
        .unwrap()
        .as_i64()
        .unwrap_or(0)
}

/// In a real browser, over HTTPS: an observer finds no submit form and a refused API
/// call; an operator submits, cancels and acknowledges an alarm, and each shows in the
/// audit trail with the operator's name; a wrong password is refused; an admin adds a
/// user; a session idle past its limit is sent to the login page; and on a dashboard
/// that joined the cell as an observer, an operator user operates nothing.
#[tokio::test(flavor = "multi_thread")]
async fn in_a_browser_each_role_does_what_it_may_and_the_audit_trail_names_them() {
    if let Err(why) = webdriver::browser_available() {
        println!("SKIPPED: the browser test needs Chromium ({why})");
        return;
    }
    let dir = tempfile::tempdir().unwrap();
    let cell = secure_cell(dir.path(), "t-dash-login");
    add_user(&cell.pki(), "olga", "observer", "observer-pw-1");
    add_user(&cell.pki(), "anna", "operator", "operator-pw-1");
    add_user(&cell.pki(), "root", "admin", "admin-pw-123");
    let dashboard = Dashboard::start(&cell, "operator.default", "https", &[]);
    // The test's own eyes: an operator's client certificate.
    let eyes = dashboard.web(&cell, Some("operator.default"));
    wait_json(&eyes, "/api/holons", "the four resources free", |h| {
        h.as_array().is_some_and(|a| {
            a.iter()
                .filter(|h| h["resource"]["state"] == "free")
                .count()
                == 4
        })
    });

    let browser = webdriver::Browser::start(&dir.path().join("profile")).unwrap();
    let within = Duration::from_secs(15);
    // Not logged in: to the login page.
    browser.goto(&dashboard.url("/")).unwrap();
    browser.wait_for("#login", within).unwrap();

    // The observer: the cell, no submit form, no PackML button, and the API refuses.
    log_in(&browser, "olga", "observer-pw-1", within);
    browser
        .wait_for("tr[data-holon=\"resource/robot1\"]", within)
        .unwrap();
    browser.wait_for("#submit-panel.hidden", within).unwrap();
    browser.wait_for("#audit-panel.hidden", within).unwrap();
    assert_eq!(browser.find("button[data-packml]").unwrap(), None);
    let (me, _) = browser.wait_for("#me", within).unwrap();
    assert_eq!(browser.text(&me).unwrap(), "olga (observer)");
    let refused = fetch_status(
        &browser,
        "/api/orders",
        r#"{method: "POST", headers: {"content-type": "application/json"}, body: JSON.stringify({product: "breaker"})}"#,
    );
    assert_eq!(refused, 403, "an observer's submit");
    let (logout, _) = browser.wait_for("#logout", within).unwrap();
    browser.click(&logout).unwrap();

    // A wrong password: refused, said so on the page.
    log_in(&browser, "anna", "not-her-password", within);
    let (error, _) = browser.wait_for("#error:not(.hidden)", within).unwrap();
    assert!(
        browser
            .text(&error)
            .unwrap()
            .contains("wrong user name or password"),
        "{}",
        browser.text(&error).unwrap()
    );

    // The operator: submits from the form, cancels a waiting order, acknowledges an
    // alarm.
    log_in(&browser, "anna", "operator-pw-1", within);
    browser
        .wait_for("#submit-panel:not(.hidden)", within)
        .unwrap();
    let (count, _) = browser.wait_for("#count", within).unwrap();
    browser.type_into(&count, "1").unwrap();
    browser.wait_for("#submit button", within).unwrap();
    // Sent twice before any answer (a double click): one work order, one order.
    browser
        .execute(
            "const f = document.getElementById('submit'); f.requestSubmit(); f.requestSubmit();",
        )
        .unwrap();
    let (said, _) = browser.wait_for("#submitted", within).unwrap();
    let started = Instant::now();
    let order = loop {
        let text = browser.text(&said).unwrap();
        if let Some(order) = text.strip_prefix("submitted ") {
            break order.to_string();
        }
        assert!(started.elapsed() < within, "no order submitted: {text}");
        std::thread::sleep(Duration::from_millis(50));
    };
    wait_json(&eyes, "/api/orders", "the submitted order done", |o| {
        o.as_array().is_some_and(|a| {
            a.iter()
                .any(|o| o["holon"] == format!("order/{order}") && o["status"] == "done")
        })
    });
    let listed = eyes.call("GET", "/api/orders", "").json();
    assert_eq!(
        listed.as_array().map(Vec::len),
        Some(1),
        "the form sent twice made orders twice: {listed}"
    );
    // The order-node's log names who asked.
    let log = std::fs::read_to_string(cell.dir.join("logs/orders1.log")).unwrap();
    assert!(
        log.lines().any(|l| l.contains("work order accepted")
            && l.contains("dashboard operator.default for anna")),
        "the order-node's log does not name anna"
    );
    // An order that waits for a product nobody serves, cancelled from its row.
    let waiting = eyes.call(
        "POST",
        "/api/orders",
        r#"{"product":"widget","count":1,"queue":true}"#,
    );
    assert_eq!(waiting.status, 200, "{waiting:?}");
    let waiting = waiting.json()["orders"][0].as_str().unwrap().to_string();
    browser.execute("window.confirm = () => true;").unwrap();
    let (cancel, _) = browser
        .wait_for(&format!("button[data-cancel=\"{waiting}\"]"), within)
        .unwrap();
    browser.click(&cancel).unwrap();
    let (answer, _) = browser.wait_for("#cancel-answer", within).unwrap();
    let started = Instant::now();
    while browser.text(&answer).unwrap().is_empty() {
        assert!(
            started.elapsed() < within,
            "the page never told how the cancel went"
        );
        std::thread::sleep(Duration::from_millis(50));
    }
    println!("the page says: {}", browser.text(&answer).unwrap());
    wait_json(&eyes, "/api/orders", "the waiting order cancelled", |o| {
        o.as_array().is_some_and(|a| {
            a.iter()
                .any(|o| o["holon"] == format!("order/{waiting}") && o["status"] == "cancelled")
        })
    });
    // An alarm: robot2's process dies (cell up starts it again).
    let pid = resource_pid(cell.keys.cell(), "robot2").expect("robot2's process");
    nix::sys::signal::kill(
        nix::unistd::Pid::from_raw(pid),
        nix::sys::signal::Signal::SIGKILL,
    )
    .unwrap();
    let (ack, _) = browser.wait_for("button[data-ack]", WAIT).unwrap();
    browser.click(&ack).unwrap();
    wait_json(
        &eyes,
        "/api/events",
        "the alarm acknowledged by anna",
        |e| {
            e.as_array().is_some_and(|e| {
                e.iter().any(|e| {
                    e["text"]
                        .as_str()
                        .is_some_and(|t| t.starts_with("acknowledged by anna:"))
                })
            })
        },
    );
    // Each is in the audit trail on the page, with her name.
    browser
        .wait_for("#audit-panel:not(.hidden)", within)
        .unwrap();
    for action in [
        "login",
        "login_failed",
        "submit",
        "cancel",
        "acknowledge_alarm",
    ] {
        let row = format!("tr[data-audit-who=\"anna\"][data-audit-action=\"{action}\"]");
        let started = Instant::now();
        while browser.find(&row).unwrap().is_none() {
            assert!(
                started.elapsed() < within,
                "no {action} by anna in the audit trail"
            );
            let (refresh, _) = browser.wait_for("#audit-refresh", within).unwrap();
            browser.click(&refresh).unwrap();
            std::thread::sleep(Duration::from_millis(200));
        }
    }
    let (logout, _) = browser.wait_for("#logout", within).unwrap();
    browser.click(&logout).unwrap();

    // The admin adds a user from the page.
    log_in(&browser, "root", "admin-pw-123", within);
    browser
        .wait_for("#users-panel:not(.hidden)", within)
        .unwrap();
    browser.wait_for("tr[data-user=\"anna\"]", within).unwrap();
    let (field, _) = browser.wait_for("#new-user", within).unwrap();
    browser.type_into(&field, "bert").unwrap();
    let (field, _) = browser.wait_for("#new-password", within).unwrap();
    browser.type_into(&field, "bert-pw-123").unwrap();
    let (add, _) = browser.wait_for("#add-user button", within).unwrap();
    browser.click(&add).unwrap();
    browser.wait_for("tr[data-user=\"bert\"]", within).unwrap();
    let mut bert = dashboard.web(&cell, None);
    assert_eq!(bert.login("bert", "bert-pw-123").status, 200);
    assert_eq!(bert.call("GET", "/api/me", "").json()["role"], "operator");
    let (logout, _) = browser.wait_for("#logout", within).unwrap();
    browser.click(&logout).unwrap();
    // The whole trail, as JSON lines, for an operator.
    let export = eyes.call("GET", "/api/audit.jsonl", "");
    assert_eq!(export.status, 200);
    let records: Vec<serde_json::Value> = export
        .body
        .lines()
        .map(|l| serde_json::from_str(l).unwrap())
        .collect();
    assert!(records
        .iter()
        .any(|r| r["who"] == "root" && r["action"] == "user_add" && r["target"] == "bert"));
    assert!(records
        .iter()
        .any(|r| r["who"] == "anna" && r["action"] == "submit" && r["outcome"] == "done"));
    assert!(records
        .iter()
        .any(|r| r["who"] == "olga" && r["action"] == "submit" && r["outcome"] == "refused"));

    // A session idle past its limit: back to the login page.
    let brief = Dashboard::start(
        &cell,
        "operator.default",
        "https",
        &["--session-idle-s", "2"],
    );
    browser.goto(&brief.url("/")).unwrap();
    log_in(&browser, "anna", "operator-pw-1", within);
    browser
        .wait_for("tr[data-holon=\"resource/robot1\"]", within)
        .unwrap();
    std::thread::sleep(Duration::from_secs(3));
    browser.goto(&brief.url("/")).unwrap();
    browser.wait_for("#login", within).unwrap();
    let url = browser.execute("return location.href;").unwrap();
    assert!(
        url.as_str().is_some_and(|u| u.contains("why=idle")),
        "{url}"
    );

    // A dashboard that joined as an observer: an operator user operates nothing.
    let watching = Dashboard::start(&cell, "observer.default", "https", &[]);
    let mut anna = watching.web(&cell, None);
    assert_eq!(anna.login("anna", "operator-pw-1").status, 200);
    assert_eq!(anna.call("GET", "/api/me", "").json()["may_operate"], false);
    let refused = anna.call("POST", "/api/orders", r#"{"product":"breaker"}"#);
    assert_eq!(refused.status, 403, "{refused:?}");
    assert!(refused.body.contains("read-only"), "{}", refused.body);
}

/// HTTPS and logins at the HTTP level: plain HTTP only redirects; nobody without a
/// session or a certificate gets anything; client certificates log in with their
/// identity's role; the cookie is HttpOnly, SameSite=Strict and Secure; the two
/// attacks of a foreign web page fail with a live session too; failed logins are
/// slowed, locked out and counted; the users file and the trail are the owner's only,
/// and a users file others can read stops the dashboard at its start.
#[tokio::test(flavor = "multi_thread")]
async fn https_logins_certificates_lockouts_and_file_modes() {
    let dir = tempfile::tempdir().unwrap();
    let cell = secure_cell(dir.path(), "t-dash-https");
    add_user(&cell.pki(), "anna", "operator", "operator-pw-1");
    let dashboard = Dashboard::start(&cell, "operator.default", "https", &[]);
    let port = dashboard.address.rsplit_once(':').unwrap().1.to_string();

    // Plain HTTP on the same port: a redirect, nothing else.
    let plain = Web::plain(&dashboard.address);
    let answer = plain.call("GET", "/api/orders?x=1", "");
    assert_eq!(answer.status, 308, "{answer:?}");
    assert_eq!(
        answer.header("location").as_deref(),
        Some(dashboard.url("/api/orders?x=1").as_str())
    );
    // HTTPS without a session or a certificate: nothing but the way to log in.
    let nobody = dashboard.web(&cell, None);
    assert_eq!(nobody.call("GET", "/api/view", "").status, 401);
    assert_eq!(nobody.call("GET", "/metrics", "").status, 401);
    let page = nobody.call("GET", "/", "");
    assert_eq!(page.status, 303, "{page:?}");
    assert_eq!(page.header("location").as_deref(), Some("/login?why=login"));
    assert_eq!(nobody.call("GET", "/login", "").status, 200);

    // Client certificates of the cell CA log in with their identity's role.
    let operator = dashboard.web(&cell, Some("operator.default"));
    let me = operator.call("GET", "/api/me", "").json();
    assert_eq!(me["who"], "cert:operator.default");
    assert_eq!(me["role"], "operator");
    assert_eq!(me["may_operate"], true);
    let observer = dashboard.web(&cell, Some("observer.default"));
    assert_eq!(
        observer.call("GET", "/api/me", "").json()["role"],
        "observer"
    );
    let refused = observer.call("POST", "/api/orders", r#"{"product":"breaker"}"#);
    assert_eq!(refused.status, 403, "{refused:?}");
    // Cancelling an order nobody made: the order-node refuses, and so does the page.
    let unknown = operator.call("POST", "/api/orders/orders1-999/cancel", "{}");
    assert_eq!(unknown.status, 409, "{unknown:?}");
    assert!(unknown.body.contains("unknown_order"), "{}", unknown.body);
    // A resource's certificate is of the cell CA but no person: not a login.
    let robot = dashboard.web(&cell, Some("resource.robot1"));
    assert_eq!(robot.call("GET", "/api/me", "").status, 401);

    // A password login: the cookie a script cannot read, sent to this site only, over
    // HTTPS only.
    let mut anna = dashboard.web(&cell, None);
    let login = anna.login("anna", "operator-pw-1");
    assert_eq!(login.status, 200, "{login:?}");
    let cookie = login.header("set-cookie").unwrap();
    for flag in ["HttpOnly", "SameSite=Strict", "Secure"] {
        assert!(cookie.contains(flag), "{flag} missing: {cookie}");
    }
    assert_eq!(anna.call("GET", "/api/me", "").json()["who"], "anna");
    // The attacks of a foreign page fail with her session too: a rebound Host, and a
    // cross-site form post.
    let evil_host = format!("evil.example:{port}");
    let rebound = anna.raw("GET", "/api/orders", &evil_host, &[], "").unwrap();
    assert_eq!(rebound.status, 421);
    let form = [
        ("content-type", "application/x-www-form-urlencoded"),
        ("origin", "https://evil.example"),
    ];
    let forged = anna
        .raw("POST", "/api/alarms/1/ack", &dashboard.address, &form, "")
        .unwrap();
    assert_eq!(forged.status, 403);
    // Logged out: the session is gone.
    assert_eq!(anna.call("POST", "/api/logout", "{}").status, 204);
    assert_eq!(anna.call("GET", "/api/me", "").status, 401);

    // A wrong password waits its second; five failures from one address (four of them
    // for anna) lock that address out, anna's right password included.
    let mut guesser = dashboard.web(&cell, None);
    let started = Instant::now();
    assert_eq!(guesser.login("anna", "guess-0").status, 401);
    assert!(started.elapsed() >= Duration::from_secs(1), "not slowed");
    assert_eq!(guesser.login("nobody", "guess-1").status, 401);
    for guess in 2..5 {
        assert_eq!(guesser.login("anna", &format!("guess-{guess}")).status, 401);
    }
    let locked = guesser.login("anna", "operator-pw-1");
    assert_eq!(locked.status, 429, "{locked:?}");
    assert!(locked.header("retry-after").is_some());
    assert!(
        locked.body.contains("too many failed logins"),
        "{}",
        locked.body
    );
    let metrics = operator.call("GET", "/metrics", "").body;
    let failed: u64 = metrics
        .lines()
        .find_map(|l| l.strip_prefix("holarchy_dashboard_logins_failed_total "))
        .and_then(|v| v.trim().parse().ok())
        .unwrap();
    assert!(failed >= 6, "{failed}");
    let trail = std::fs::read_to_string(cell.pki().join("audit.jsonl")).unwrap();
    assert!(
        trail
            .lines()
            .filter(|l| l.contains("\"login_failed\""))
            .count()
            >= 6,
        "{trail}"
    );
    assert!(!trail.contains("operator-pw-1") && !trail.contains("guess-"));
    assert!(
        trail.lines().any(|l| l.contains("\"cancel\"")
            && l.contains("orders1-999")
            && l.contains("\"outcome\":\"refused\"")),
        "{trail}"
    );

    // The files: the owner's only; a users file others can read stops a dashboard.
    let users = cell.pki().join("users.toml");
    assert_eq!(mode(&users), 0o600);
    assert_eq!(mode(&cell.pki().join("audit.jsonl")), 0o600);
    std::fs::set_permissions(&users, std::fs::Permissions::from_mode(0o644)).unwrap();
    let refused = Dashboard::command(&cell, "operator.default")
        .output()
        .unwrap();
    assert!(!refused.status.success());
    let stderr = String::from_utf8_lossy(&refused.stderr);
    assert!(stderr.contains("chmod 600"), "{stderr}");
}

/// A dashboard without login serves loopback only: asked to listen on every address
/// without a users file, it refuses at the start and says what to do; with a users file
/// but without HTTPS, too.
#[test]
fn a_dashboard_without_login_listens_on_loopback_only() {
    let refused = Command::new(bin("cell"))
        .args([
            "dashboard",
            "--cell",
            "t-open",
            "--connect",
            "tcp/127.0.0.1:1",
        ])
        .args(["--listen", "0.0.0.0:0", "--operator"])
        .output()
        .unwrap();
    assert!(!refused.status.success());
    let stderr = String::from_utf8_lossy(&refused.stderr);
    assert!(stderr.contains("loopback only"), "{stderr}");
    assert!(stderr.contains("--users"), "{stderr}");
    // Nor do passwords travel over plain HTTP off loopback.
    let dir = tempfile::tempdir().unwrap();
    let users = dir.path().join("users.toml");
    let refused = Command::new(bin("cell"))
        .args([
            "dashboard",
            "--cell",
            "t-open",
            "--connect",
            "tcp/127.0.0.1:1",
        ])
        .args(["--listen", "0.0.0.0:0", "--operator"])
        .arg("--users")
        .arg(&users)
        .output()
        .unwrap();
    assert!(!refused.status.success());
    let stderr = String::from_utf8_lossy(&refused.stderr);
    assert!(stderr.contains("serve HTTPS"), "{stderr}");
}
