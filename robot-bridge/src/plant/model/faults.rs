//! The plant's faults, played on its control port: a jammed track, a pallet that stops
//! reporting, a transporter's e-stop, a pallet taken out of service.

use schemas::layout::Dock;

use super::{Place, Plant};

impl Plant {
    /// Presses (true) or releases (false) `resource`'s e-stop at the plant's time: a
    /// transporter's moves stand still while it is pressed, then go on with the time
    /// they had left.
    pub fn estop(&mut self, resource: &str, pressed: bool) {
        if pressed {
            self.estopped
                .entry(resource.to_string())
                .or_insert(self.clock);
            return;
        }
        let Some(since) = self.estopped.remove(resource) else {
            return;
        };
        let stood = self.clock.saturating_sub(since);
        for p in self.pallets.values_mut().filter(|p| p.conveyor == resource) {
            match &mut p.place {
                Place::Track { due, .. } | Place::Docking { due, .. }
                    if *due > since && *due != u64::MAX =>
                {
                    *due += stood;
                }
                _ => {}
            }
        }
        for t in self
            .transit
            .values_mut()
            .filter(|t| t.transporter == resource)
        {
            if let Some(due) = t.arrives_ms.as_mut().filter(|due| **due > since) {
                *due += stood;
            }
        }
        self.settle();
    }

    /// Jams the track that ends at `at` (true), or clears it (false), at the plant's
    /// time. An error if the layout has no such conveyor stopper.
    pub fn jam(&mut self, at: Dock, jammed: bool) -> Result<(), String> {
        let known = self
            .layout
            .conveyor(&at.conveyor)
            .is_some_and(|c| c.stoppers.iter().any(|s| s.name == at.stopper));
        if !known {
            return Err(format!("{at}: no such conveyor stopper in the plant"));
        }
        if jammed {
            self.jammed.insert(at);
        } else {
            self.jammed.remove(&at);
        }
        self.settle();
        Ok(())
    }

    /// `pallet` stops reporting (true) or reports again (false).
    pub fn silence(&mut self, pallet: &str, silent: bool) -> Result<(), String> {
        if !self.pallets.contains_key(pallet) {
            return Err(format!("{pallet}: no such pallet in the plant"));
        }
        if silent {
            self.silent.insert(pallet.to_string());
        } else {
            self.silent.remove(pallet);
        }
        Ok(())
    }

    /// Takes `pallet` out of service (true) or puts it back (false), at the plant's
    /// time. A free pallet goes at once; one carrying a part, or on its way to fetch
    /// one, once it is free again (it finishes what it carries). One put back is free
    /// at once, for the part that has waited longest for a pallet.
    pub fn retire(&mut self, pallet: &str, out: bool) -> Result<(), String> {
        let Some(p) = self.pallets.get_mut(pallet) else {
            return Err(format!("{pallet}: no such pallet in the plant"));
        };
        let happened = match (out, &p.place) {
            (true, Place::Parked) => {
                p.place = Place::Retired;
                true
            }
            (true, Place::Retired) => false,
            (true, _) => {
                p.retiring = true;
                false
            }
            (false, Place::Retired) => {
                p.place = Place::Parked;
                true
            }
            (false, _) => {
                p.retiring = false;
                false
            }
        };
        if happened {
            self.happened.push(super::Happening::Retired {
                pallet: pallet.to_string(),
                out,
            });
        }
        self.settle();
        Ok(())
    }

    /// Whether `pallet` stopped reporting.
    pub fn is_silent(&self, pallet: &str) -> bool {
        self.silent.contains(pallet)
    }
}
