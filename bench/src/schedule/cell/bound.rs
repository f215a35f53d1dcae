//! The lower bound on a cell scenario's makespan, from the cell's own files: what no
//! schedule can beat, whatever the control does (docs/scheduling.md, "The lower
//! bound").
//!
//! - **A job's bound**: its steps' processing, each on the station of its choice, plus
//!   the unobstructed travel between consecutive stations (none when two steps share
//!   one), from the cell's entry to its first station and from its last to the exit:
//!   the cheapest such path over every choice of stations, plus the job's release.
//! - **A station set's bound**: for every set K of stations, the work of every step
//!   that only stations of K can do (each at its fastest on K), shared evenly over K,
//!   after the earliest any of those steps can begin and before the least any of them
//!   leaves to do: no schedule finishes that work sooner. A step's **head** is the least
//!   time from its job's release to its start (the steps before it, each at its
//!   fastest, and the least travel between them, from the entry); its **tail** the
//!   least time from its end to the job's exit (the steps after it and the travel,
//!   to the exit). So the set's bound is the least head of its steps, plus their work
//!   shared over K, plus the least tail: the machines of K can begin none of that work
//!   before the least head, and whichever step of it ends last still has its job's
//!   tail to go. K = {M1} is the loading unit's load and unload of every job.
//! - The bound is the larger of the longest job's and the busiest set's.
//!
//! Processing times are the plant's (`plant.toml`: a controller's `action_ms`, else
//! its `delay_ms`, for each action of the service's steps), travel the conveyor's
//! (distance over speed, one way round the loop, without docking): both as the plant
//! runs them at 1x, in plant time. Stations are those the scenario ever has (those
//! started and those hot-added): a station added mid-run only lowers the bound.

use std::collections::{BTreeMap, BTreeSet};
use std::path::Path;

use anyhow::{anyhow, bail, Context, Result};
use schemas::layout::{CellLayout, ConveyorSpec, LocationRole, TransporterSpec};

/// A station: what it offers and how long each service takes on it.
#[derive(Debug, Clone)]
pub struct Station {
    pub name: String,
    /// Its conveyor stopper (where its port docks).
    pub stopper: String,
    /// Per service type, its processing time in plant ms.
    pub services: BTreeMap<String, u64>,
}

/// What the bound is computed from.
#[derive(Debug, Clone)]
pub struct CellModel {
    pub stations: Vec<Station>,
    /// The transporter's holon name, and the conveyor parts ride on between stations.
    pub transporter: String,
    pub conveyor: ConveyorSpec,
    /// The stoppers where parts enter and leave the cell.
    pub entry: String,
    pub exit: String,
    /// Per product, its steps' service types in order.
    pub products: BTreeMap<String, Vec<String>>,
}

/// The bound, with its parts.
#[derive(Debug, Clone, serde::Serialize)]
pub struct Bound {
    /// The lower bound on the makespan, plant ms from the first release.
    pub makespan_ms: u64,
    /// The longest job's bound (its release, processing and least travel).
    pub job_ms: u64,
    /// The busiest station set's bound, and that set.
    pub stations_ms: u64,
    pub busiest: Vec<String>,
    /// The busiest set's least head and least tail (in `stations_ms`): before its work
    /// can begin, and after it has ended.
    pub busiest_head_ms: u64,
    pub busiest_tail_ms: u64,
}

impl CellModel {
    /// The model of the cell in `dir`: its plant file's layout and times, its product
    /// configs, and the station configs of `stations` (the resource holons the
    /// scenario ever has; the transporter among them is not a station).
    pub fn load(dir: &Path, stations: &[String], products: &[String]) -> Result<CellModel> {
        let plant_path = dir.join("plant.toml");
        let plant = robot_bridge::plant::read(&plant_path).map_err(|e| anyhow!("{e}"))?;
        let layout =
            robot_bridge::plant::layout_of(&plant_path, &plant).map_err(|e| anyhow!("{e}"))?;
        let (transporter, conveyor, entry, exit) = conveyor_of(&layout)?;
        let mut model = CellModel {
            stations: Vec::new(),
            transporter,
            conveyor,
            entry,
            exit,
            products: BTreeMap::new(),
        };
        for name in stations.iter().filter(|s| **s != model.transporter) {
            let controller = plant
                .controllers
                .iter()
                .find(|c| &c.resource == name)
                .ok_or_else(|| anyhow!("plant.toml: no controller for station {name}"))?;
            let config = read_toml(&dir.join(format!("{name}.toml")))?;
            let stopper = layout
                .parts
                .get(name)
                .and_then(|p| p.locations.iter().find_map(|l| l.dock.clone()))
                .map(|d| d.stopper)
                .ok_or_else(|| anyhow!("{name}: no location docked at the conveyor"))?;
            let mut services = BTreeMap::new();
            for (service, spec) in config
                .get("services")
                .and_then(|s| s.as_table())
                .into_iter()
                .flatten()
            {
                let mut took = 0;
                for step in spec
                    .get("steps")
                    .and_then(|s| s.as_array())
                    .into_iter()
                    .flatten()
                {
                    let action = step.get("action").and_then(|a| a.as_str()).unwrap_or("");
                    took += controller
                        .action_ms
                        .get(action)
                        .copied()
                        .unwrap_or(controller.delay_ms);
                }
                services.insert(service.clone(), took);
            }
            model.stations.push(Station {
                name: name.clone(),
                stopper,
                services,
            });
        }
        for product in products {
            let config = read_toml(&dir.join(format!("{product}.toml")))?;
            let steps = config
                .get("steps")
                .and_then(|s| s.as_array())
                .ok_or_else(|| anyhow!("{product}.toml: no [[steps]]"))?
                .iter()
                .map(|s| {
                    s.get("service_type")
                        .and_then(|t| t.as_str())
                        .map(str::to_string)
                        .ok_or_else(|| anyhow!("{product}.toml: a step without service_type"))
                })
                .collect::<Result<Vec<_>>>()?;
            model.products.insert(product.clone(), steps);
        }
        Ok(model)
    }

    fn travel(&self, from: &str, to: &str) -> u64 {
        self.conveyor.travel_ms(from, to).unwrap_or(0)
    }

    /// The least time one job of `product` takes from its entry to its exit.
    pub fn job_ms(&self, product: &str) -> Result<u64> {
        let steps = self
            .products
            .get(product)
            .ok_or_else(|| anyhow!("unknown product {product}"))?;
        // Per station the job may be at after the steps so far, the least time to
        // there (the entry before the first).
        let mut best: Vec<(String, u64)> = vec![(self.entry.clone(), 0)];
        for service in steps {
            let next: Vec<(String, u64)> = self
                .stations
                .iter()
                .filter_map(|s| s.services.get(service).map(|took| (s, *took)))
                .map(|(station, took)| {
                    let arrive = best
                        .iter()
                        .map(|(at, t)| t + self.travel(at, &station.stopper))
                        .min()
                        .unwrap_or(0);
                    (station.stopper.clone(), arrive + took)
                })
                .collect();
            if next.is_empty() {
                bail!("{product}: no station offers {service}");
            }
            best = next;
        }
        Ok(best
            .iter()
            .map(|(at, t)| t + self.travel(at, &self.exit))
            .min()
            .unwrap_or(0))
    }

    /// The bound for jobs of these products released at these plant ms (from the
    /// first release).
    pub fn bound(&self, jobs: &[(String, u64)]) -> Result<Bound> {
        let mut job_ms = 0;
        let mut each = BTreeMap::new();
        for (product, released) in jobs {
            if !each.contains_key(product) {
                each.insert(product.clone(), self.job_ms(product)?);
            }
            job_ms = job_ms.max(released + each[product]);
        }
        let busiest = self.busiest_set(jobs)?;
        Ok(Bound {
            makespan_ms: job_ms.max(busiest.bound_ms),
            job_ms,
            stations_ms: busiest.bound_ms,
            busiest: busiest.stations,
            busiest_head_ms: busiest.head_ms,
            busiest_tail_ms: busiest.tail_ms,
        })
    }

    /// For each step of a job of `product`, its head (the least time from the job's
    /// release until the step can begin) and its tail (the least time from its end to
    /// the job's exit).
    fn heads_and_tails(&self, product: &str) -> Result<Vec<(u64, u64)>> {
        let steps = self
            .products
            .get(product)
            .ok_or_else(|| anyhow!("unknown product {product}"))?;
        let able = |service: &str| -> Result<Vec<(&str, u64)>> {
            let able: Vec<(&str, u64)> = self
                .stations
                .iter()
                .filter_map(|s| s.services.get(service).map(|t| (s.stopper.as_str(), *t)))
                .collect();
            if able.is_empty() {
                bail!("{product}: no station offers {service}");
            }
            Ok(able)
        };
        // Forward: per station the job may be at, the least time to have done the
        // steps so far there.
        let mut heads = Vec::with_capacity(steps.len());
        let mut done: Vec<(&str, u64)> = vec![(self.entry.as_str(), 0)];
        for service in steps {
            let arrivals: Vec<(&str, u64, u64)> = able(service)?
                .into_iter()
                .map(|(stopper, took)| {
                    let arrive = done
                        .iter()
                        .map(|(at, t)| t + self.travel(at, stopper))
                        .min()
                        .unwrap_or(0);
                    (stopper, arrive, took)
                })
                .collect();
            heads.push(arrivals.iter().map(|(_, a, _)| *a).min().unwrap_or(0));
            done = arrivals
                .into_iter()
                .map(|(stopper, arrive, took)| (stopper, arrive + took))
                .collect();
        }
        // Backward: per station the job may be at, the least time from arriving there
        // (the step's work included) to the exit.
        let mut tails = vec![0; steps.len()];
        let mut ahead: Vec<(&str, u64)> = vec![(self.exit.as_str(), 0)];
        for (k, service) in steps.iter().enumerate().rev() {
            let rests: Vec<(&str, u64, u64)> = able(service)?
                .into_iter()
                .map(|(stopper, took)| {
                    let rest = ahead
                        .iter()
                        .map(|(at, t)| self.travel(stopper, at) + t)
                        .min()
                        .unwrap_or(0);
                    (stopper, rest, took)
                })
                .collect();
            tails[k] = rests.iter().map(|(_, r, _)| *r).min().unwrap_or(0);
            ahead = rests
                .into_iter()
                .map(|(stopper, rest, took)| (stopper, rest + took))
                .collect();
        }
        Ok(heads.into_iter().zip(tails).collect())
    }

    /// The station set whose bound (its steps' least head, the work only it can do
    /// shared over it, its steps' least tail) is the largest.
    fn busiest_set(&self, jobs: &[(String, u64)]) -> Result<BusiestSet> {
        // Every step of every job: the stations able to do it, its work on each, its
        // head (from the first release) and its tail.
        struct Step {
            able: BTreeSet<usize>,
            fastest: u64,
            head: u64,
            tail: u64,
        }
        let mut steps: Vec<Step> = Vec::new();
        let mut each = BTreeMap::new();
        for (product, released) in jobs {
            if !each.contains_key(product) {
                each.insert(product.clone(), self.heads_and_tails(product)?);
            }
            for (service, (head, tail)) in self.products[product].iter().zip(&each[product]) {
                let able: BTreeMap<usize, u64> = self
                    .stations
                    .iter()
                    .enumerate()
                    .filter_map(|(i, s)| s.services.get(service).map(|t| (i, *t)))
                    .collect();
                steps.push(Step {
                    able: able.keys().copied().collect(),
                    fastest: able.values().copied().min().unwrap_or(0),
                    head: released + head,
                    tail: *tail,
                });
            }
        }
        let n = self.stations.len().min(16);
        let mut best = BusiestSet::default();
        for mask in 1u32..(1 << n) {
            let set: BTreeSet<usize> = (0..n).filter(|i| mask & (1 << i) != 0).collect();
            let only: Vec<&Step> = steps
                .iter()
                .filter(|s| !s.able.is_empty() && s.able.is_subset(&set))
                .collect();
            let Some(head_ms) = only.iter().map(|s| s.head).min() else {
                continue;
            };
            let tail_ms = only.iter().map(|s| s.tail).min().unwrap_or(0);
            let work: u64 = only.iter().map(|s| s.fastest).sum();
            let bound_ms = head_ms + work / set.len() as u64 + tail_ms;
            if bound_ms > best.bound_ms {
                best = BusiestSet {
                    bound_ms,
                    stations: set.iter().map(|i| self.stations[*i].name.clone()).collect(),
                    head_ms,
                    tail_ms,
                };
            }
        }
        Ok(best)
    }
}

/// The station set with the largest bound.
#[derive(Debug, Default)]
struct BusiestSet {
    /// Its bound, plant ms from the first release.
    bound_ms: u64,
    stations: Vec<String>,
    /// Its steps' least head and least tail.
    head_ms: u64,
    tail_ms: u64,
}

/// The conveyor of the layout (its holon and spec) and its entry's and exit's stoppers.
fn conveyor_of(layout: &CellLayout) -> Result<(String, ConveyorSpec, String, String)> {
    let (conveyor, spec) = layout
        .parts
        .iter()
        .find_map(|(name, part)| match &part.transporter {
            Some(TransporterSpec::Conveyor(c)) => Some((name.clone(), c.clone())),
            _ => None,
        })
        .ok_or_else(|| anyhow!("the layout has no conveyor"))?;
    let stopper_of = |roles: &[LocationRole]| {
        layout
            .locations()
            .map(|(_, l)| l)
            .filter(|l| roles.contains(&l.role))
            .filter_map(|l| l.dock.as_ref())
            .find(|d| d.conveyor == conveyor)
            .map(|d| d.stopper.clone())
    };
    let entry = stopper_of(&[LocationRole::Entry, LocationRole::EntryExit])
        .ok_or_else(|| anyhow!("{conveyor}: no entry docked on it"))?;
    let exit = stopper_of(&[LocationRole::Exit, LocationRole::EntryExit])
        .ok_or_else(|| anyhow!("{conveyor}: no exit docked on it"))?;
    Ok((conveyor, spec, entry, exit))
}

fn read_toml(path: &Path) -> Result<toml::Table> {
    let text =
        std::fs::read_to_string(path).with_context(|| format!("cannot read {}", path.display()))?;
    toml::from_str(&text).with_context(|| format!("{}", path.display()))
}

#[cfg(test)]
mod tests {
    use super::*;

    fn aip() -> CellModel {
        let dir = holarchy_tests::workspace_root().join("deploy/cells/aip-primeca");
        let stations: Vec<String> = ["m1", "m2", "m3", "m4", "m5", "m6", "monorail"]
            .map(String::from)
            .to_vec();
        let products: Vec<String> = ["b", "e", "l", "t", "a", "i", "p"]
            .map(String::from)
            .to_vec();
        CellModel::load(&dir, &stations, &products).unwrap()
    }

    #[test]
    fn a_job_takes_its_processing_and_its_least_travel() {
        let model = aip();
        assert_eq!(model.transporter, "monorail");
        assert_eq!((model.entry.as_str(), model.exit.as_str()), ("in", "out"));
        // T: load 10, axis 20 x2, r_comp 20, l_comp 20 (all on one robot), inspection 5,
        // unload 10; the monorail at 500 mm/s from the entry (0 mm) to M1 (300), on to a
        // robot and M5 (9140), round to M1 (16865 + 300) and to the exit (600).
        let travel = 600 + (9140 - 300) * 1000 / 500 + (16865 + 300 - 9140) * 1000 / 500 + 600;
        assert_eq!(model.job_ms("t").unwrap(), 105_000 + travel);
    }

    #[test]
    fn one_of_each_product_is_bound_by_the_assembly_robots() {
        let jobs: Vec<(String, u64)> = ["b", "e", "l", "t", "a", "i", "p"]
            .map(|p| (p.to_string(), 0))
            .to_vec();
        let bound = aip().bound(&jobs).unwrap();
        // The 25 axis and r_comp operations of 20 s, which only M2 and M3 do, shared by
        // the two (250 s); none can begin before a part is loaded at M1 and taken on to
        // M2 (0.6 s to M1, load 10 s, 4.83 s on); and after the last of them the least
        // a job still has to do is E's or T's l_comp on M4 (2.32 s there, 20 s), the
        // inspection on M5 (4.83 s, 5 s), the unload at M1 (16.05 s round, 10 s) and
        // the exit (0.6 s).
        assert_eq!(bound.busiest, ["m2", "m3"]);
        assert_eq!(bound.busiest_head_ms, 600 + 10_000 + 4_830);
        assert_eq!(
            bound.busiest_tail_ms,
            2_320 + 20_000 + 4_830 + 5_000 + 16_050 + 10_000 + 600
        );
        assert_eq!(
            bound.stations_ms,
            bound.busiest_head_ms + 25 * 20_000 / 2 + bound.busiest_tail_ms
        );
        assert_eq!(bound.makespan_ms, bound.stations_ms.max(bound.job_ms));
        // Beside it, the work alone: the 39 assembly operations shared by M2, M3 and
        // M4 (260 s), the bound before heads and tails were counted.
        assert!(bound.stations_ms > 39 * 20_000 / 3);
    }
}
