//! Pallets for parts: a conveyor's move boards its part on the part's own pallet or a
//! free one brought to it; with none free the part waits for one, and a freed pallet
//! is parked again (or taken out of service, if it is to be).

use schemas::layout::LocationId;

use super::{Bound, Happening, Load, Place, Plant};

impl Plant {
    /// A conveyor's move begins: the part's pallet docked at `from` (or a parked one,
    /// brought there) is bound for `to`. Returns the part on its pallet, or without a
    /// pallet (its old carrier parked) when none is free: it waits at `from` for one
    /// ([`Plant::pallets_found`]).
    pub(super) fn board(
        &mut self,
        conveyor: &str,
        mut load: Load,
        from: &LocationId,
        to: &LocationId,
    ) -> Load {
        let docked_here = load.carrier.as_ref().filter(|c| {
            self.pallets
                .get(*c)
                .is_some_and(|p| p.conveyor == conveyor && p.place == Place::Docked(from.clone()))
        });
        let pallet = match docked_here {
            Some(pallet) => pallet.clone(),
            None => {
                // Off its old pallet (parked again), onto a free one, brought to `from`.
                self.park(load.carrier.take());
                match self.parked(conveyor) {
                    Some(parked) => parked,
                    None => return load,
                }
            }
        };
        self.board_onto(conveyor, &pallet, load, from, to)
    }

    /// A free pallet of `conveyor`, if one is parked.
    fn parked(&self, conveyor: &str) -> Option<String> {
        self.pallets
            .iter()
            .find(|(_, p)| p.conveyor == conveyor && p.place == Place::Parked)
            .map(|(id, _)| id.clone())
    }

    /// `pallet`, docked at `from`, takes the part of `load` to `to`.
    fn board_onto(
        &mut self,
        conveyor: &str,
        pallet: &str,
        mut load: Load,
        from: &LocationId,
        to: &LocationId,
    ) -> Load {
        let pallet = pallet.to_string();
        let stopper = self.stopper_of(conveyor, to).expect("a routed location");
        let p = self
            .pallets
            .get_mut(&pallet)
            .expect("a pallet of the plant");
        p.place = Place::Docked(from.clone());
        p.part = Some(load.part.clone());
        p.bound = Some(Bound {
            to: to.clone(),
            stopper,
            ridden_mm: 0,
        });
        p.stopped = false;
        load.carrier = Some(pallet);
        if let Some(at) = self
            .held
            .get_mut(from)
            .and_then(|loads| loads.iter_mut().find(|l| l.part == load.part))
        {
            at.carrier = load.carrier.clone();
        }
        load
    }

    /// Parts waiting for a pallet get the free ones, the longest waiting first (a
    /// conveyor's e-stop holds them back too).
    pub(super) fn pallets_found(&mut self) {
        let mut waiting: Vec<(u64, String)> = self
            .transit
            .iter()
            .filter(|(_, t)| t.awaits_pallet && !t.stopped)
            .filter(|(_, t)| !self.estopped.contains_key(&t.transporter))
            .map(|(part, t)| (t.began_ms, part.clone()))
            .collect();
        waiting.sort();
        for (_, part) in waiting {
            let t = &self.transit[&part];
            let (conveyor, from, to) = (t.transporter.clone(), t.from.clone(), t.to.clone());
            let Some(pallet) = self.parked(&conveyor) else {
                continue;
            };
            let load = self.transit[&part].load.clone();
            let load = self.board_onto(&conveyor, &pallet, load, &from, &to);
            let t = self.transit.get_mut(&part).expect("found above");
            t.load = load;
            t.awaits_pallet = false;
        }
    }

    /// `pallet` is free: back in its conveyor's park (or out of service, if it is to
    /// be taken out).
    pub(super) fn park(&mut self, pallet: Option<String>) {
        let Some(pallet) = pallet else { return };
        if let Some(p) = self.pallets.get_mut(&pallet) {
            p.place = if p.retiring {
                p.retiring = false;
                self.happened.push(Happening::Retired {
                    pallet: pallet.clone(),
                    out: true,
                });
                Place::Retired
            } else {
                Place::Parked
            };
            p.part = None;
            p.bound = None;
            p.stopped = false;
            p.waiting_since = None;
        }
    }
}
