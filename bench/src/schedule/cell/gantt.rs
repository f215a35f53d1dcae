//! A run's Gantt chart as SVG: one row per station, then one per shuttle, each action
//! a bar from its begin to its end in plant time, coloured by the product of its part.

use std::collections::BTreeMap;

use robot_bridge::plant::trace::TraceRecord;

/// One colour per product, in the order products are first met.
const COLOURS: [&str; 8] = [
    "#4e79a7", "#f28e2b", "#e15759", "#76b7b2", "#59a14f", "#edc948", "#b07aa1", "#9c755f",
];

const WIDTH: f64 = 1200.0;
const LEFT: f64 = 110.0;
const ROW: f64 = 18.0;
const TOP: f64 = 40.0;

/// The chart of `trace` from plant ms `start`: `product_of` names each part's product,
/// `transporter` is the resource whose moves are drawn on their shuttles' rows.
pub fn svg(
    title: &str,
    trace: &[TraceRecord],
    start: u64,
    product_of: &BTreeMap<String, String>,
    transporter: &str,
) -> String {
    let end = trace
        .iter()
        .map(|r| r.end_ms)
        .max()
        .unwrap_or(start)
        .max(start + 1);
    let rows = rows_of(trace, transporter);
    let mut products: Vec<&String> = product_of.values().collect();
    products.sort();
    products.dedup();
    let colour = |part: Option<&String>| {
        part.and_then(|p| product_of.get(p))
            .and_then(|p| products.iter().position(|q| *q == p))
            .map_or("#bbbbbb", |i| COLOURS[i % COLOURS.len()])
    };
    let span = (end - start) as f64;
    let x = |ms: u64| LEFT + (ms.saturating_sub(start)) as f64 / span * (WIDTH - LEFT - 10.0);
    let height = TOP + ROW * rows.len() as f64 + 40.0;
    let mut out = String::new();
    line(
        &mut out,
        format!(
            r##"<svg xmlns="http://www.w3.org/2000/svg" width="{WIDTH}" height="{height}" font-family="sans-serif" font-size="11">"##
        ),
    );
    line(
        &mut out,
        r##"<rect width="100%" height="100%" fill="white"/>"##.to_string(),
    );
    line(
        &mut out,
        format!(
            r##"<text x="{LEFT}" y="16" font-size="13">{}</text>"##,
            escape(title)
        ),
    );
    for (i, name) in rows.iter().enumerate() {
        let y = TOP + ROW * i as f64;
        line(
            &mut out,
            format!(
                r##"<text x="4" y="{}">{}</text><line x1="{LEFT}" x2="{}" y1="{}" y2="{}" stroke="#eeeeee"/>"##,
                y + ROW * 0.7,
                escape(name),
                WIDTH - 10.0,
                y + ROW,
                y + ROW
            ),
        );
    }
    for record in trace.iter().filter(|r| r.end_ms >= start) {
        let name = if record.resource == transporter {
            shuttle_row(record)
        } else {
            record.resource.clone()
        };
        let Some(i) = rows.iter().position(|r| *r == name) else {
            continue;
        };
        let (x0, x1) = (x(record.begin_ms), x(record.end_ms));
        line(
            &mut out,
            format!(
                r##"<rect x="{x0:.1}" y="{:.1}" width="{:.1}" height="{:.1}" fill="{}"><title>{} {} {} {:.1}-{:.1} s</title></rect>"##,
                TOP + ROW * i as f64 + 2.0,
                (x1 - x0).max(0.5),
                ROW - 4.0,
                colour(record.part.as_ref()),
                escape(record.part.as_deref().unwrap_or("-")),
                escape(&record.resource),
                escape(&record.action),
                record.begin_ms.saturating_sub(start) as f64 / 1000.0,
                record.end_ms.saturating_sub(start) as f64 / 1000.0,
            ),
        );
    }
    // The time axis, in plant seconds, with ten ticks.
    let axis = TOP + ROW * rows.len() as f64 + 14.0;
    for tick in 0..=10 {
        let ms = start + (end - start) * tick / 10;
        line(
            &mut out,
            format!(
                r##"<text x="{:.1}" y="{axis}" text-anchor="middle">{:.0} s</text>"##,
                x(ms),
                (ms - start) as f64 / 1000.0
            ),
        );
    }
    legend(&mut out, &products, axis);
    out.push_str("</svg>\n");
    out
}

/// Appends `text` and a line break.
fn line(out: &mut String, text: String) {
    out.push_str(&text);
    out.push('\n');
}

/// The chart's rows: the stations by name, then the shuttles by name.
fn rows_of(trace: &[TraceRecord], transporter: &str) -> Vec<String> {
    let mut stations: Vec<String> = trace
        .iter()
        .filter(|r| r.resource != transporter)
        .map(|r| r.resource.clone())
        .collect();
    stations.sort();
    stations.dedup();
    let mut shuttles: Vec<String> = trace
        .iter()
        .filter(|r| r.resource == transporter)
        .map(shuttle_row)
        .collect();
    shuttles.sort();
    shuttles.dedup();
    stations.extend(shuttles);
    stations
}

/// The products' colours, below the axis at `axis`.
fn legend(out: &mut String, products: &[&String], axis: f64) {
    let mut legend = LEFT;
    for (i, product) in products.iter().enumerate() {
        line(
            out,
            format!(
                r##"<rect x="{legend}" y="{}" width="10" height="10" fill="{}"/><text x="{}" y="{}">{}</text>"##,
                axis + 8.0,
                COLOURS[i % COLOURS.len()],
                legend + 14.0,
                axis + 17.0,
                escape(product)
            ),
        );
        legend += 24.0 + 7.0 * product.len() as f64;
    }
}

/// A move's row: its shuttle (the transporter's own name when it carried none).
fn shuttle_row(record: &TraceRecord) -> String {
    record
        .carrier
        .clone()
        .unwrap_or_else(|| record.resource.clone())
}

fn escape(text: &str) -> String {
    text.replace('&', "&amp;")
        .replace('<', "&lt;")
        .replace('>', "&gt;")
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_chart_has_a_row_per_station_and_shuttle_and_a_bar_per_action() {
        let record = |resource: &str, carrier: Option<&str>, begin_ms, end_ms| TraceRecord {
            resource: resource.into(),
            action: "x".into(),
            part: Some("o-1".into()),
            carrier: carrier.map(String::from),
            begin_ms,
            end_ms,
            done: true,
        };
        let trace = vec![
            record("belt", Some("belt/p2"), 1_000, 2_000),
            record("m2", None, 2_000, 4_000),
            record("m1", None, 4_000, 5_000),
        ];
        let products = BTreeMap::from([("o-1".to_string(), "b".to_string())]);
        let chart = svg("a <run>", &trace, 1_000, &products, "belt");
        assert_eq!(rows_of(&trace, "belt"), ["m1", "m2", "belt/p2"]);
        assert_eq!(chart.matches("<title>o-1 ").count(), 3);
        assert!(chart.contains("a &lt;run&gt;"), "{chart}");
        // Its first bar starts at the left edge, its last ends at the right one.
        assert!(
            chart.contains(&format!(r#"<rect x="{LEFT:.1}""#)),
            "{chart}"
        );
        assert!(chart.starts_with("<svg") && chart.trim_end().ends_with("</svg>"));
    }
}
