//! A log destination written by a thread of its own: the task that logs formats its line
//! and queues it; the thread writes what has queued up in one write call.
//!
//! The thread sleeps on a condition variable while nothing is queued and is woken only
//! then: it does not spin or yield between lines (a channel's receiver does, and at a
//! dozen lines per service cycle its yields took a third of a resource holon's CPU on
//! two cores, docs/benchmarks.md). Nothing is dropped: a logger that finds
//! [`LINES_IN_FLIGHT`] lines queued waits until the thread has taken them. Dropping the
//! [`WriterGuard`] writes out what is left and ends the thread.

use std::io::Write;
use std::sync::{Arc, Condvar, Mutex, MutexGuard};
use std::thread::JoinHandle;

use tracing_subscriber::fmt::MakeWriter;

/// Lines queued for one writer thread before logging waits for it.
pub const LINES_IN_FLIGHT: usize = 1024;

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
    /// The thread sleeps on `queued`.
    sleeping: bool,
    /// The guard was dropped: write out and end.
    closed: bool,
}

impl Shared {
    fn lock(&self) -> MutexGuard<'_, Queue> {
        // A logger that panicked mid-push left whole lines only: the queue is usable.
        self.queue.lock().unwrap_or_else(|e| e.into_inner())
    }

    /// Queues one line, waiting while the queue is full.
    fn push(&self, line: &[u8]) {
        let mut queue = self.lock();
        while queue.lines >= LINES_IN_FLIGHT && !queue.closed {
            queue = self.taken.wait(queue).unwrap_or_else(|e| e.into_inner());
        }
        queue.bytes.extend_from_slice(line);
        queue.lines += 1;
        if queue.sleeping {
            queue.sleeping = false;
            self.queued.notify_one();
        }
    }
}

/// The thread's loop: takes whatever is queued and writes it in one call.
fn write_out<W: Write>(shared: &Shared, mut destination: W) {
    let mut batch = Vec::new();
    loop {
        let closed = {
            let mut queue = shared.lock();
            while queue.lines == 0 && !queue.closed {
                queue.sleeping = true;
                queue = shared.queued.wait(queue).unwrap_or_else(|e| e.into_inner());
            }
            std::mem::swap(&mut batch, &mut queue.bytes);
            queue.lines = 0;
            shared.taken.notify_all();
            queue.closed
        };
        if !batch.is_empty() {
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
            .spawn(move || write_out(&shared, destination))?
    };
    Ok((
        LineWriter {
            shared: Arc::clone(&shared),
        },
        WriterGuard {
            shared,
            thread: Some(thread),
        },
    ))
}

/// One event's line, queued when dropped.
pub struct EventLine {
    shared: Arc<Shared>,
    line: Vec<u8>,
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
            self.shared.push(&self.line);
        }
    }
}

impl<'a> MakeWriter<'a> for LineWriter {
    type Writer = EventLine;

    fn make_writer(&'a self) -> EventLine {
        EventLine {
            shared: Arc::clone(&self.shared),
            line: Vec::with_capacity(256),
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
}
