//! What the journal keeps of the agenda manager: everything that must survive a crash,
//! owned ([`AgendaRecord`], read back when the journal is opened) or borrowed
//! ([`AgendaRecordRef`], what a write serialises, in the same form).

use std::collections::{BTreeMap, BTreeSet};

use schemas::layout::LocationId;
use schemas::Service;
use serde::Serialize;

use super::{AgendaMachine, Booking, Job, PlaceHold};
use crate::machine::packml::PackmlUnit;

/// What the journal keeps of the agenda manager.
#[derive(Debug, Clone, PartialEq, Default, serde::Serialize, serde::Deserialize)]
pub struct AgendaRecord {
    pub bookings: Vec<Booking>,
    /// The job that was executing (the first begun, when several were): after a crash
    /// it is reported `interrupted`.
    pub current: Option<Job>,
    /// The other jobs that were executing at the same time (a controller that runs
    /// several at once); absent when none was.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub more_running: Vec<Job>,
    pub undelivered: Vec<Service>,
    /// The PackML unit; absent from journals written before PackML (the config's
    /// initial state then applies).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub packml: Option<PackmlUnit>,
    /// The places held at its locations (absent from journals written before them).
    #[serde(default, skip_serializing_if = "BTreeMap::is_empty")]
    pub places: BTreeMap<LocationId, Vec<PlaceHold>>,
    /// A conveyor's carriers out of service (absent when none is, and from journals
    /// written before them).
    #[serde(default, skip_serializing_if = "BTreeSet::is_empty")]
    pub carriers_out: BTreeSet<String>,
}

/// The record borrowed from the agenda manager: written as an [`AgendaRecord`] is,
/// without copying it first.
#[derive(Debug, Serialize)]
pub struct AgendaRecordRef<'a> {
    pub bookings: &'a [Booking],
    pub current: Option<&'a Job>,
    #[serde(skip_serializing_if = "<[Job]>::is_empty")]
    pub more_running: &'a [Job],
    pub undelivered: &'a [Service],
    pub packml: &'a PackmlUnit,
    #[serde(skip_serializing_if = "BTreeMap::is_empty")]
    pub places: &'a BTreeMap<LocationId, Vec<PlaceHold>>,
    #[serde(skip_serializing_if = "BTreeSet::is_empty")]
    pub carriers_out: &'a BTreeSet<String>,
}

impl AgendaMachine {
    /// What the journal keeps, as a copy.
    pub fn record(&self) -> AgendaRecord {
        AgendaRecord {
            bookings: self.bookings.clone(),
            current: self.running.first().cloned(),
            more_running: self.running.iter().skip(1).cloned().collect(),
            undelivered: self.undelivered.clone(),
            packml: Some(self.packml.clone()),
            places: self.places.held().clone(),
            carriers_out: self.carriers.out().clone(),
        }
    }

    /// What the journal keeps, borrowed (for a write).
    pub fn record_ref(&self) -> AgendaRecordRef<'_> {
        AgendaRecordRef {
            bookings: &self.bookings,
            current: self.running.first(),
            more_running: self.running.get(1..).unwrap_or_default(),
            undelivered: &self.undelivered,
            packml: &self.packml,
            places: self.places.held(),
            carriers_out: self.carriers.out(),
        }
    }

    /// Whether `other` keeps the same record, compared in place: whether a journal
    /// write would change anything.
    pub fn same_record(&self, other: &AgendaMachine) -> bool {
        self.bookings == other.bookings
            && self.running == other.running
            && self.undelivered == other.undelivered
            && self.packml == other.packml
            && self.places.held() == other.places.held()
            && self.carriers.out() == other.carriers.out()
    }

    /// Whether this is the record it keeps, compared in place.
    pub fn keeps(&self, record: &AgendaRecord) -> bool {
        self.bookings == record.bookings
            && self.running.first() == record.current.as_ref()
            && self.running.get(1..).unwrap_or_default() == record.more_running.as_slice()
            && self.undelivered == record.undelivered
            && record.packml.as_ref() == Some(&self.packml)
            && self.places.held() == &record.places
            && self.carriers.out() == &record.carriers_out
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_borrowed_record_is_written_as_the_owned_one_is() {
        let agenda = crate::machine::agenda::tests::agenda_for_record();
        let owned = serde_json::to_value(agenda.record()).unwrap();
        let borrowed = serde_json::to_value(agenda.record_ref()).unwrap();
        assert_eq!(owned, borrowed);
        // (A job's parameters are not written: they are read again from its `info`.)
        let _: AgendaRecord = serde_json::from_value(borrowed).unwrap();
        let record = agenda.record();
        assert!(agenda.keeps(&record));
        assert!(agenda.same_record(&agenda.clone()));
        let mut other = agenda.clone();
        other.bookings.pop();
        assert!(!agenda.same_record(&other));
        assert!(!other.keeps(&record));
    }
}
