//! The driver with a holon of its own (what it is told, in what order) on a real zenoh
//! router: stopped, a hand-over refused and one made, and a leadership lost twice (a
//! new round, then the end).

use std::sync::{Arc, Mutex};
use std::time::Duration;

use tokio::sync::Notify;
use tokio_util::sync::CancellationToken;

use super::*;
use crate::presence::Holder;
use crate::takeover::{Request, TakeoverError};

/// Every wait of these tests, at most.
const WAIT: Duration = Duration::from_secs(20);

const KEY: &str = "holarchy/t/alive/resource/fake";
const SERVICE: &str = "holarchy/t/resource/fake/service";

/// What the holon and its leadership were told, in order. (A test's shared record.)
#[derive(Clone, Default)]
struct Said(Arc<Mutex<Vec<String>>>);

impl Said {
    fn say(&self, what: impl Into<String>) {
        self.0.lock().expect("the record").push(what.into());
    }

    fn all(&self) -> Vec<String> {
        self.0.lock().expect("the record").clone()
    }
}

/// A holon with nothing of its own but what it is told.
struct Fake {
    said: Said,
    /// Why it refuses a hand-over, if it does.
    refuse: Option<String>,
}

struct FakeWork {
    said: Said,
    refuse: Option<String>,
}

impl Behaviour for Fake {
    type Grant = ();
    type Work = FakeWork;
    type Error = LifeError;

    async fn start(&mut self, start: Start<()>) -> Result<FakeWork, LifeError> {
        self.said
            .say(format!("start handed_over={}", start.handed_over));
        Ok(FakeWork {
            said: self.said.clone(),
            refuse: self.refuse.clone(),
        })
    }
}

impl Work for FakeWork {
    type Event = ();
    type Error = LifeError;

    async fn serving(&mut self) {
        self.said.say("serving");
    }

    async fn next(&mut self) -> Next<(), LifeError> {
        std::future::pending().await
    }

    async fn handle(&mut self, _event: ()) {}

    fn refusal(&self, _request: &Request) -> Option<String> {
        self.refuse.clone()
    }

    async fn prepare(&mut self, _wait: Duration) -> Result<(), String> {
        self.said.say("prepare");
        Ok(())
    }

    async fn leave(&mut self, how: &Leaving) {
        self.said.say(format!("leave {how:?}"));
    }

    fn stand_in(&self) -> StandInSpec {
        StandInSpec {
            keys: vec![(SERVICE.to_string(), false)],
            answer: unavailable_answer("resource/fake", "handed over".into()),
        }
    }

    async fn stop(self, how: &Leaving) -> Result<(), LifeError> {
        self.said.say(format!("stop {how:?}"));
        Ok(())
    }
}

/// A leadership the test deposes: claims again after the first deposition, ends the
/// process after the second.
struct Deposable {
    said: Said,
    depose: Arc<Notify>,
    rounds: usize,
}

impl Leadership<Fake> for Deposable {
    async fn win(
        &mut self,
        _life: &Life,
        _session: &zenoh::Session,
        _shutdown: &CancellationToken,
    ) -> Result<Option<()>, LifeError> {
        self.rounds += 1;
        self.said.say(format!("win {}", self.rounds));
        Ok(Some(()))
    }

    async fn lost(&mut self) -> String {
        self.depose.notified().await;
        format!("deposed in round {}", self.rounds)
    }

    async fn deposed(&mut self, why: &str) -> Result<(), LifeError> {
        self.said.say(format!("deposed: {why}"));
        match self.rounds {
            1 => Ok(()),
            _ => Err(LifeError::Zenoh(why.to_string())),
        }
    }
}

/// A router on a free port, and the settings of a client of it.
async fn cell() -> (zenoh::Session, ZenohSettings) {
    let mut attempts = 0;
    loop {
        let port = std::net::TcpListener::bind("127.0.0.1:0")
            .and_then(|l| l.local_addr())
            .expect("a free port")
            .port();
        let endpoint = format!("tcp/127.0.0.1:{port}");
        let router = ZenohSettings {
            mode: crate::Mode::Router,
            listen: vec![endpoint.clone()],
            ..ZenohSettings::default()
        };
        match router.open("router.test", WAIT).await {
            Ok(session) => {
                let client = ZenohSettings {
                    connect: vec![endpoint],
                    ..ZenohSettings::default()
                };
                return (session, client);
            }
            Err(e) if attempts < 5 => {
                attempts += 1;
                eprintln!("another port ({e})");
            }
            Err(e) => panic!("cannot open a router: {e}"),
        }
    }
}

fn process(zenoh: &ZenohSettings) -> Process<'_> {
    Process {
        life: Life {
            presence_key: KEY.into(),
            holder: "resource/fake".into(),
            version: "test",
            take_over: None,
            data_dir: None,
            startup_timeout: WAIT,
        },
        zenoh,
        tls_identity: "resource.fake".into(),
    }
}

/// Waits until the holon's token is there (or, `false`, gone).
async fn token(router: &zenoh::Session, there: bool) {
    let waited = tokio::time::timeout(WAIT, async {
        loop {
            let tokens = crate::presence::tokens(router, KEY, Duration::from_secs(2))
                .await
                .expect("a liveliness query");
            if tokens.is_empty() != there {
                return;
            }
            tokio::time::sleep(Duration::from_millis(20)).await;
        }
    })
    .await;
    assert!(waited.is_ok(), "the token never became {there}");
}

/// Waits until the record has `what` at least `times` times.
async fn said_at_least(said: &Said, what: &str, times: usize) {
    let waited = tokio::time::timeout(WAIT, async {
        while said.all().iter().filter(|s| *s == what).count() < times {
            tokio::time::sleep(Duration::from_millis(10)).await;
        }
    })
    .await;
    assert!(
        waited.is_ok(),
        "{what:?} not said {times} times: {:?}",
        said.all()
    );
}

fn request() -> Request {
    Request {
        successor: Holder {
            host: "test".into(),
            pid: 1,
            zid: "0".into(),
            since: 0,
        },
        version: "next".into(),
        data_dir: None,
        wait_ms: 1000,
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_stopped_holon_leaves_withdraws_its_token_and_stops() {
    let (router, client) = cell().await;
    let said = Said::default();
    let fake = Fake {
        said: said.clone(),
        refuse: None,
    };
    let shutdown = CancellationToken::new();
    let life = run(
        process(&client),
        fake,
        LivelinessClaim::default(),
        shutdown.clone(),
    );
    let test = async {
        token(&router, true).await;
        shutdown.cancel();
    };
    let (ended, ()) = tokio::time::timeout(WAIT, async { tokio::join!(life, test) })
        .await
        .expect("the holon stops");
    ended.expect("a stop ends Ok");
    token(&router, false).await;
    assert_eq!(
        said.all(),
        [
            "start handed_over=false",
            "serving",
            "leave Stopping",
            "stop Stopping"
        ]
    );
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_hand_over_the_holon_cannot_make_is_refused_and_it_serves_on() {
    let (router, client) = cell().await;
    let said = Said::default();
    let fake = Fake {
        said: said.clone(),
        refuse: Some("its journal cannot be written".into()),
    };
    let shutdown = CancellationToken::new();
    let life = run(
        process(&client),
        fake,
        LivelinessClaim::default(),
        shutdown.clone(),
    );
    let test = async {
        token(&router, true).await;
        let asked = takeover::take_over(&router, KEY, "resource/fake", &request()).await;
        shutdown.cancel();
        asked
    };
    let (ended, asked) = tokio::time::timeout(WAIT, async { tokio::join!(life, test) })
        .await
        .expect("the holon stops");
    ended.expect("a stop ends Ok");
    match asked {
        Err(TakeoverError::Refused { detail, .. }) => {
            assert_eq!(detail, "its journal cannot be written")
        }
        other => panic!("not refused: {other:?}"),
    }
    assert_eq!(
        said.all(),
        [
            "start handed_over=false",
            "serving",
            "leave Stopping",
            "stop Stopping"
        ]
    );
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_hand_over_stands_in_stops_the_work_and_ends_when_the_successor_serves() {
    let (router, client) = cell().await;
    let said = Said::default();
    let fake = Fake {
        said: said.clone(),
        refuse: None,
    };
    let shutdown = CancellationToken::new();
    let life = run(
        process(&client),
        fake,
        LivelinessClaim::default(),
        shutdown.clone(),
    );
    let test = async {
        token(&router, true).await;
        let taken = takeover::take_over(&router, KEY, "resource/fake", &request()).await;
        // Released: the predecessor's token is gone; a stand-in answers its service.
        let stand_in = router
            .get(SERVICE)
            .timeout(Duration::from_secs(5))
            .await
            .expect("a query")
            .recv_async()
            .await
            .expect("the stand-in answers");
        let refusal = stand_in
            .result()
            .expect_err("unavailable")
            .payload()
            .to_bytes()
            .to_vec();
        // The successor serves.
        let successor = router
            .liveliness()
            .declare_token(KEY)
            .await
            .expect("the successor's token");
        (taken, refusal, successor)
    };
    let (ended, (taken, refusal, _successor)) =
        tokio::time::timeout(WAIT, async { tokio::join!(life, test) })
            .await
            .expect("the predecessor ends");
    ended.expect("the successor served: Ok");
    assert!(matches!(taken, Ok(TakenOver::From(_))), "{taken:?}");
    let refusal = String::from_utf8(refusal).expect("text");
    assert!(
        refusal.contains("unavailable") && refusal.contains("handed over"),
        "{refusal}"
    );
    assert_eq!(
        said.all(),
        [
            "start handed_over=false",
            "serving",
            "prepare",
            "leave HandingOver",
            "stop HandingOver"
        ]
    );
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_deposed_holon_steps_down_and_its_leadership_says_what_follows() {
    let (router, client) = cell().await;
    let said = Said::default();
    let fake = Fake {
        said: said.clone(),
        refuse: None,
    };
    let depose = Arc::new(Notify::new());
    let leadership = Deposable {
        said: said.clone(),
        depose: depose.clone(),
        rounds: 0,
    };
    let life = run(process(&client), fake, leadership, CancellationToken::new());
    let test = async {
        for round in 1..=2 {
            // Serving in this round: deposed (the permit waits for its `lost`).
            said_at_least(&said, "serving", round).await;
            depose.notify_one();
        }
    };
    let (ended, ()) = tokio::time::timeout(WAIT, async { tokio::join!(life, test) })
        .await
        .expect("the holon ends");
    token(&router, false).await;
    let error = ended.expect_err("deposed twice: the end");
    assert!(error.to_string().contains("deposed in round 2"), "{error}");
    let round = |n: usize| {
        [
            format!("win {n}"),
            "start handed_over=false".to_string(),
            "serving".to_string(),
            format!("leave Deposed(\"deposed in round {n}\")"),
            format!("stop Deposed(\"deposed in round {n}\")"),
            format!("deposed: deposed in round {n}"),
        ]
    };
    assert_eq!(said.all(), [round(1), round(2)].concat());
}
