//! A log destination written by a thread of its own: the task that logs formats its line
//! and queues it; the thread writes what has queued up in one write call.
//!
//! The thread is woken by a logger only when it sleeps deeply, after [`GATHER`] without a
//! line: the first line of a burst wakes it, and while lines keep coming it wakes by
//! itself every [`GATHER`] and writes what queued up meanwhile, so a busy holon's
//! loggers make no wake-up call and no thread switch on the request's path. (Woken per
//! line, with the notification made under the queue's lock, the two writer threads took
//! four thread switches per line on two cores, about 300 us of a service cycle between
//! a job's arrival and its first controller command; docs/benchmarks.md.) It never spins
//! or yields between lines either (a channel's receiver does, and at a dozen lines per
//! service cycle its yields took a third of a resource holon's CPU). A line reaches its
//! destination at most [`GATHER`] after it was logged. Nothing is dropped: a logger that
//! finds [`LINES_IN_FLIGHT`] lines queued waits until the thread has taken them, and the
//! thread is woken at once when half that many wait. Dropping the [`WriterGuard`] writes
//! out what is left and ends the thread.

mod escape;

use std::io::Write;
use std::sync::{Arc, Condvar, Mutex, MutexGuard};
use std::thread::JoinHandle;
use std::time::{Duration, Instant};

use tracing_subscriber::fmt::MakeWriter;

/// Lines queued for one writer thread before logging waits for it.
pub const LINES_IN_FLIGHT: usize = 1024;

/// How long the thread gathers lines after it wrote some before it writes again; after a
/// [`GATHER`] without a line it sleeps until a logger wakes it.
pub const GATHER: Duration = Duration::from_millis(2);

/// What the loggers and the thread share.
struct Shared {
    queue: Mutex<Queue>,
    /// Lines were queued (or the guard is dropped): the thread takes them.
    queued: Condvar,
    /// The thread took the queue: waiting loggers may queue again.
    taken: Condvar,
}

/// The lines waiting for the thread.
#[derive(Default)]
struct Queue {
    /// Their bytes, one after the other.
    bytes: Vec<u8>,
    /// How many.
    lines: usize,
    /// The thread sleeps on `queued` until a logger wakes it (not gathering).
    sleeping: bool,
    /// The guard was dropped: write out and end.
    closed: bool,
}

impl Shared {
    fn lock(&self) -> MutexGuard<'_, Queue> {
        // A logger that panicked mid-push left whole lines only: the queue is usable.
        self.queue.lock().unwrap_or_else(|e| e.into_inner())
    }

    /// Queues one line, waiting while the queue is full; wakes the thread when it sleeps
    /// deeply or half the queue waits. The thread is notified after the lock is released,
    /// so that it does not wake only to wait for the lock.
    fn push(&self, line: &[u8]) {
        let mut queue = self.lock();
        while queue.lines >= LINES_IN_FLIGHT && !queue.closed {
            queue = self.taken.wait(queue).unwrap_or_else(|e| e.into_inner());
        }
        queue.bytes.extend_from_slice(line);
        queue.lines += 1;
        let wake = queue.sleeping || queue.lines == LINES_IN_FLIGHT / 2;
        queue.sleeping = false;
        drop(queue);
        if wake {
            self.queued.notify_one();
        }
    }
}

/// The thread's loop: takes whatever is queued and writes it in one call, then gathers
/// for [`GATHER`] before it takes the queue again.
fn write_out<W: Write + ?Sized>(shared: &Shared, destination: &mut W) {
    let mut batch = Vec::new();
    let mut wrote = false;
    loop {
        let closed = {
            let mut queue = shared.lock();
            if wrote {
                let until = Instant::now() + GATHER;
                loop {
                    let now = Instant::now();
                    if queue.closed || queue.lines >= LINES_IN_FLIGHT / 2 || now >= until {
                        break;
                    }
                    queue = shared
                        .queued
                        .wait_timeout(queue, until - now)
                        .unwrap_or_else(|e| e.into_inner())
                        .0;
                }
            }
            while queue.lines == 0 && !queue.closed {
                queue.sleeping = true;
                queue = shared.queued.wait(queue).unwrap_or_else(|e| e.into_inner());
            }
            queue.sleeping = false;
            std::mem::swap(&mut batch, &mut queue.bytes);
            queue.lines = 0;
            queue.closed
        };
        shared.taken.notify_all();
        wrote = !batch.is_empty();
        if wrote {
            // Nowhere to report a failed write of the log itself: the line is lost,
            // the program goes on (as with any logger).
            if destination
                .write_all(&batch)
                .and_then(|()| destination.flush())
                .is_err()
            {
                eprintln!("cannot write {} bytes of log lines", batch.len());
            }
            batch.clear();
        }
        if closed {
            return;
        }
    }
}

/// The handle loggers write through ([`MakeWriter`]): each event's line is queued
/// whole when its writer is dropped.
#[derive(Clone)]
pub struct LineWriter {
    shared: Arc<Shared>,
    /// Whether the escape character is written as it is (a colour terminal); every
    /// other control character of an event is always escaped ([`escape`]).
    keep_esc: bool,
}

impl LineWriter {
    /// The same writer, writing the escape character as it is (for a terminal that
    /// shows the formatter's colours).
    pub fn keeping_esc(mut self, keep: bool) -> LineWriter {
        self.keep_esc = keep;
        self
    }
}

/// Ends the writer thread when dropped, after it wrote out every queued line.
#[must_use = "dropping the guard stops the log writer"]
pub struct WriterGuard {
    shared: Arc<Shared>,
    thread: Option<JoinHandle<()>>,
}

impl Drop for WriterGuard {
    fn drop(&mut self) {
        {
            let mut queue = self.shared.lock();
            queue.closed = true;
            self.shared.queued.notify_one();
            self.shared.taken.notify_all();
        }
        if let Some(thread) = self.thread.take() {
            if thread.join().is_err() {
                eprintln!("the log writer thread panicked; lines may be lost");
            }
        }
    }
}

/// A writer thread called `name` for `destination`.
pub fn spawn<W: Write + Send + 'static>(
    destination: W,
    name: &str,
) -> std::io::Result<(LineWriter, WriterGuard)> {
    let shared = Arc::new(Shared {
        queue: Mutex::new(Queue::default()),
        queued: Condvar::new(),
        taken: Condvar::new(),
    });
    let thread = {
        let shared = Arc::clone(&shared);
        std::thread::Builder::new()
            .name(name.to_string())
            .spawn(move || {
                let mut destination = destination;
                write_out(&shared, &mut destination)
            })?
    };
    Ok((
        LineWriter {
            shared: Arc::clone(&shared),
            keep_esc: false,
        },
        WriterGuard {
            shared,
            thread: Some(thread),
        },
    ))
}

/// One event's line, queued when dropped, its control characters escaped.
pub struct EventLine {
    shared: Arc<Shared>,
    line: Vec<u8>,
    keep_esc: bool,
}

impl Write for EventLine {
    fn write(&mut self, bytes: &[u8]) -> std::io::Result<usize> {
        self.line.extend_from_slice(bytes);
        Ok(bytes.len())
    }

    fn flush(&mut self) -> std::io::Result<()> {
        Ok(())
    }
}

impl Drop for EventLine {
    fn drop(&mut self) {
        if !self.line.is_empty() {
            self.shared
                .push(&escape::escaped(&self.line, self.keep_esc));
        }
    }
}

impl<'a> MakeWriter<'a> for LineWriter {
    type Writer = EventLine;

    fn make_writer(&'a self) -> EventLine {
        EventLine {
            shared: Arc::clone(&self.shared),
            line: Vec::with_capacity(256),
            keep_esc: self.keep_esc,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A destination the test reads back.
    #[derive(Clone, Default)]
    struct Sink(Arc<Mutex<Vec<u8>>>);

    impl Write for Sink {
        fn write(&mut self, bytes: &[u8]) -> std::io::Result<usize> {
            self.0.lock().unwrap().extend_from_slice(bytes);
            Ok(bytes.len())
        }
        fn flush(&mut self) -> std::io::Result<()> {
            Ok(())
        }
    }

    #[test]
    fn every_line_from_every_thread_is_written_whole_and_in_order_per_thread() {
        let sink = Sink::default();
        let (writer, guard) = spawn(sink.clone(), "log-test").unwrap();
        let threads: Vec<_> = (0..4)
            .map(|t| {
                let writer = writer.clone();
                std::thread::spawn(move || {
                    // More than the queue holds: loggers wait, nothing is dropped.
                    for n in 0..(LINES_IN_FLIGHT * 2) {
                        let mut line = writer.make_writer();
                        write!(line, "thread {t} ").unwrap();
                        writeln!(line, "line {n}").unwrap();
                    }
                })
            })
            .collect();
        for thread in threads {
            thread.join().unwrap();
        }
        drop(guard);
        let text = String::from_utf8(sink.0.lock().unwrap().clone()).unwrap();
        let lines: Vec<&str> = text.lines().collect();
        assert_eq!(lines.len(), 4 * LINES_IN_FLIGHT * 2);
        for t in 0..4 {
            let mine: Vec<&str> = lines
                .iter()
                .filter(|l| l.starts_with(&format!("thread {t} ")))
                .copied()
                .collect();
            let expected: Vec<String> = (0..LINES_IN_FLIGHT * 2)
                .map(|n| format!("thread {t} line {n}"))
                .collect();
            assert_eq!(mine, expected);
        }
    }

    #[test]
    fn dropping_the_guard_writes_out_what_is_queued() {
        let sink = Sink::default();
        let (writer, guard) = spawn(sink.clone(), "log-test").unwrap();
        for n in 0..10 {
            writeln!(writer.make_writer(), "{n}").unwrap();
        }
        drop(guard);
        assert_eq!(sink.0.lock().unwrap().len(), 20);
    }

    /// Waits, at most 5 s, until the sink holds `bytes` bytes.
    fn wait_for(sink: &Sink, bytes: usize) -> usize {
        let deadline = Instant::now() + Duration::from_secs(5);
        loop {
            let held = sink.0.lock().unwrap().len();
            if held >= bytes || Instant::now() >= deadline {
                return held;
            }
            std::thread::sleep(Duration::from_millis(1));
        }
    }

    #[test]
    fn a_line_is_written_whether_the_thread_sleeps_or_gathers() {
        let sink = Sink::default();
        let (writer, _guard) = spawn(sink.clone(), "log-test").unwrap();
        // The thread sleeps: the first line wakes it.
        writeln!(writer.make_writer(), "a").unwrap();
        assert_eq!(wait_for(&sink, 2), 2, "the first line is written");
        // It gathers now: the next line is taken without being woken.
        writeln!(writer.make_writer(), "b").unwrap();
        assert_eq!(
            wait_for(&sink, 4),
            4,
            "a line logged while it gathers is written"
        );
        // After a quiet spell it sleeps again, and a line wakes it again.
        std::thread::sleep(GATHER * 5);
        writeln!(writer.make_writer(), "c").unwrap();
        assert_eq!(
            wait_for(&sink, 6),
            6,
            "a line after a quiet spell is written"
        );
        assert_eq!(sink.0.lock().unwrap().as_slice(), b"a\nb\nc\n");
    }
}
