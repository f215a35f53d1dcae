//! What `bench schedule` prints of a cell run: a table row per run, with its orders'
//! endings, what its processes used and its critical path under it.

use super::CellRun;

/// The table's header.
pub fn print_header() {
    println!(
        "{:<14} {:<13} {:>5} {:>10} {:>9} {:>7} {:>10} {:>10} {:>10} {:>8}  utilisation",
        "scenario",
        "mode",
        "scale",
        "makespan",
        "bound",
        "gap",
        "mean flow",
        "rush flow",
        "tardiness",
        "shuttles"
    );
}

/// A run's row, its orders and processes, and its critical path.
pub fn print_row(run: &CellRun) {
    let s = |ms: u64| format!("{:.1}s", ms as f64 / 1000.0);
    let f = &run.figures;
    let utilisation: Vec<String> = f
        .utilisation
        .iter()
        .map(|(station, u)| format!("{station} {:.0}%", u * 100.0))
        .collect();
    println!(
        "{:<14} {:<13} {:>5} {:>10} {:>9} {:>6.1}% {:>10} {:>10} {:>10} {:>7.0}%  {}",
        run.scenario,
        run.mode.as_str(),
        run.time_scale,
        s(f.makespan_ms),
        s(run.bound.makespan_ms),
        run.gap * 100.0,
        s(f.mean_flow_ms),
        f.rush_mean_flow_ms.map_or("-".into(), s),
        s(f.mean_tardiness_ms),
        f.shuttle_utilisation * 100.0,
        utilisation.join(" ")
    );
    let processes: Vec<String> = run
        .processes
        .iter()
        .map(|p| {
            format!(
                "{} {:.1}s/{:.0}MiB",
                p.name,
                p.cpu_s,
                p.peak_rss_kib as f64 / 1024.0
            )
        })
        .collect();
    println!(
        "    orders: {}; wall {:.1}s; CPU time / peak resident memory: {}",
        run.endings.summary(),
        run.wall_s,
        processes.join(", ")
    );
    if let Some(path) = &run.critical_path {
        let longest = path.longest.as_ref().map_or(String::new(), |w| {
            format!(
                "; the longest {} before {}'s {} of {} at {}",
                s(w.ms),
                w.resource,
                w.action,
                w.part,
                s(w.began_ms)
            )
        });
        let share = |ms: u64| ms as f64 * 100.0 / f.makespan_ms.max(1) as f64;
        println!(
            "    critical path: {} actions, {} ({:.1}% of the makespan) waiting on the control, {} ({:.2}%) of it its latency{}",
            path.actions,
            s(path.idle_ms),
            share(path.idle_ms),
            s(path.latency_ms),
            share(path.latency_ms),
            longest
        );
    }
}
