//! What `robot-sim --check` adds to a dialect's checks: that robot-sim can play the
//! controller from the file, so a rehearsal rehearses what the holon will meet. Every
//! reply it writes is read back by the holon as that reply, and a status reply says
//! each state.

use schemas::ControllerState;

use super::{messages, Dialect, Outcome, Status, Values};

impl Dialect {
    /// The status reply that says `state`, with the values to write it: the first, in
    /// the order of the file, whose message, written with `state` and `message`, the
    /// holon reads back (section 4.4's step 3) as that state.
    pub fn status_reply_for(
        &self,
        state: ControllerState,
        message: &str,
    ) -> Option<(usize, Values)> {
        let mut values = Values::default();
        values.set("state", state.as_str().into());
        values.set("message", message.into());
        let says = |index: usize| {
            let Some(body) = &self.replies[index].body else {
                return false;
            };
            let Ok(bytes) = self.write(body, &values) else {
                return false;
            };
            let Ok(parsed) = self.parse(&bytes) else {
                return false;
            };
            matches!(
                self.read_unsolicited(&parsed),
                Ok(Some((read, _, Some(read_state)))) if read == index && read_state == state
            )
        };
        let found = self
            .replies
            .iter()
            .enumerate()
            .filter(|(_, r)| r.outcome == Outcome::Status)
            .map(|(index, _)| index)
            .find(|&index| says(index));
        found.map(|index| (index, values))
    }

    /// A status message in the controller's shape that says a state the dialect does not
    /// describe (`robot-sim --unknown-state-every`): the reply that says `ready`, as
    /// written, with one of its words (the last that works) replaced by `word`, such that
    /// the result still parses (its framing's bytes are well formed) and no reply of the
    /// file takes it (each misses it or finds a value outside its table), so the holon
    /// can only read it as a protocol error (section 4.4). `STATE IDLE` becomes `STATE
    /// HOMING`. None when no word can be replaced so (a binary dialect).
    pub fn undescribed_status(&self, word: &str) -> Option<Vec<u8>> {
        if matches!(
            self.frame_codec().framing,
            super::framing::Framing::LengthPrefix { .. }
        ) {
            return None;
        }
        let (index, values) = self.status_reply_for(ControllerState::Ready, "")?;
        let bytes = self
            .write(self.replies[index].body.as_ref()?, &values)
            .ok()?;
        let text = String::from_utf8(bytes).ok()?;
        let is_word = |c: char| c.is_ascii_alphanumeric() || c == '_';
        let mut words = Vec::new();
        let mut start = None;
        for (at, c) in text.char_indices().chain([(text.len(), ' ')]) {
            match (start, is_word(c)) {
                (None, true) => start = Some(at),
                (Some(from), false) => {
                    words.push(from..at);
                    start = None;
                }
                _ => {}
            }
        }
        words.into_iter().rev().find_map(|range| {
            let mut candidate = text.clone();
            candidate.replace_range(range, word);
            let parsed = self.parse(candidate.as_bytes()).ok()?;
            let taken = (0..self.replies.len())
                .any(|reply| matches!(self.read_reply(reply, &parsed), Ok(Some(_))));
            (!taken).then(|| candidate.into_bytes())
        })
    }

    /// Checks that robot-sim can write every reply this dialect needs, that the holon
    /// reads each back as that reply (a `regex` that does not match its own `text`, a
    /// value its table cannot read, are found here, not on the first line), and that a
    /// status reply says `ready` (else the controller is never used): `robot-sim
    /// --check`. A status reply for `fault` or `estop` missing is a warning
    /// ([`Dialect::warnings`]).
    pub fn check_simulatable(&self) -> Result<(), String> {
        for reply in &self.replies {
            if reply.body.is_none() {
                return Err(format!(
                    "reply {}: robot-sim writes replies from `text`, and this one has only a regex",
                    reply.name
                ));
            }
        }
        for index in 0..self.replies.len() {
            self.check_reads_back(index)?;
        }
        if self.status != Status::Connection
            && self
                .status_reply_for(ControllerState::Ready, "text")
                .is_none()
        {
            return Err(
                "no status reply says ready: written with state = \"ready\", none is read back as ready (the holon tries them in the order of the file); the controller would never be used"
                    .into(),
            );
        }
        Ok(())
    }

    /// Reply `index`, written by robot-sim with sample values, is read back by the holon
    /// as that reply, with the values written. A reply whose text cannot be written with
    /// the samples (an action missing from its table) is not checked here.
    fn check_reads_back(&self, index: usize) -> Result<(), String> {
        let reply = &self.replies[index];
        let Some(body) = &reply.body else {
            return Ok(());
        };
        let mut values = Values::default();
        values.set("id", "7".into());
        values.set("action", "pick".into());
        values.set("program", "p1".into());
        values.set("result", "picking_done".into());
        values.set("message", "sample message".into());
        values.set("state", "ready".into());
        values.set("pose", String::new());
        for name in ["x", "y", "z", "a", "b", "c"] {
            values.set(name, self.format.number(1.5));
        }
        // A table's first value stands in where the samples are not in it.
        for template in messages::templates_of(body) {
            for (name, table) in template.names() {
                let Some(table) = table else { continue };
                let fits = values
                    .get(&name)
                    .is_some_and(|v| self.enums.encode(&table, v).is_ok());
                if !fits {
                    if let Some(first) = self.enums.first_value(&table) {
                        values.set(&name, first.to_string());
                    }
                }
            }
        }
        let Ok(bytes) = self.write(body, &values) else {
            return Ok(());
        };
        let shown = String::from_utf8_lossy(&bytes).into_owned();
        let parsed = self.parse(&bytes).map_err(|e| {
            format!(
                "reply {}: robot-sim writes {shown:?}, which the holon cannot read: {e}",
                reply.name
            )
        })?;
        match self.read_reply(index, &parsed) {
            Ok(Some(read)) => {
                // Only what the text writes can come back as written.
                let written: Vec<String> = messages::templates_of(body)
                    .iter()
                    .flat_map(|t| t.names())
                    .map(|(n, _)| n)
                    .collect();
                for (name, value) in read.iter() {
                    if !written.iter().any(|n| n == name) {
                        continue;
                    }
                    if values.get(name).is_some_and(|v| v != value) {
                        return Err(format!(
                            "reply {}: the holon reads {name} = {value:?} from {shown:?}, written with {name} = {:?}",
                            reply.name,
                            values.get(name).unwrap_or_default()
                        ));
                    }
                }
                Ok(())
            }
            Ok(None) => Err(format!(
                "reply {}: robot-sim writes {shown:?} from its text, which the holon does not read as this reply{}",
                reply.name,
                if reply.regex.is_some() { " (its regex does not match it)" } else { "" }
            )),
            Err(why) => Err(format!(
                "reply {}: robot-sim writes {shown:?} from its text, which the holon reads wrongly: {why}",
                reply.name
            )),
        }
    }
}

impl Dialect {
    /// The states of `fault` and `estop` no status reply can say (a warning: the holon
    /// never learns of them, and `--fault-after` cannot play them).
    pub(super) fn unsayable_states(&self) -> Vec<ControllerState> {
        if self.status == Status::Connection {
            return vec![];
        }
        [ControllerState::Fault, ControllerState::Estop]
            .into_iter()
            .filter(|&state| self.status_reply_for(state, "text").is_none())
            .collect()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn an_undescribed_state_is_the_ready_status_with_another_word_that_no_reply_takes() {
        let job_ack_end = std::fs::read_to_string(concat!(
            env!("CARGO_MANIFEST_DIR"),
            "/../deploy/dialects/examples/job-ack-end.toml"
        ))
        .unwrap();
        let dialect = Dialect::from_toml(&job_ack_end, "job-ack-end.toml").unwrap();
        assert_eq!(
            dialect.undescribed_status("HOMING").as_deref(),
            Some(&b"STATE HOMING"[..])
        );
        // A table's state: the value outside the table.
        let ur = Dialect::shipped("ur-dashboard").unwrap();
        let said = String::from_utf8(ur.undescribed_status("HOMING").unwrap()).unwrap();
        assert!(said.contains("HOMING"), "{said}");
        let parsed = ur.parse(said.as_bytes()).unwrap();
        assert!(ur.read_unsolicited(&parsed).is_err(), "{said}");
        // A binary dialect's status has no word to change.
        assert!(Dialect::shipped("simple-message")
            .unwrap()
            .undescribed_status("HOMING")
            .is_none());
    }
}
