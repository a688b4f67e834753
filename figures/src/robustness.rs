//! The robustness figure: success against disturbance level, one panel per disturbance, one
//! line per controller, from the table `docs/bench/robustness.sh` writes.

use std::collections::BTreeMap;
use std::path::Path;

use plotters::prelude::*;

use crate::FigureError;

/// One row of the table: a controller under one disturbance at one level.
#[derive(Clone, Debug, PartialEq)]
pub struct RobustnessRow {
    /// The disturbance, e.g. `wind (m/s)`.
    pub disturbance: String,
    /// Its level (0: nominal).
    pub level: f64,
    /// The controller, e.g. `generalist`.
    pub controller: String,
    /// Success over the test set's deployments, in [0, 1].
    pub success: f64,
}

/// Reads `disturbance,level,controller,success[,…]` rows after a header.
pub fn read_rows(path: &Path) -> Result<Vec<RobustnessRow>, FigureError> {
    let text = std::fs::read_to_string(path).map_err(|source| FigureError::Io { what: format!("reading {}", path.display()), source })?;
    let mut rows = Vec::new();
    for (i, line) in text.lines().enumerate().skip(1).filter(|(_, l)| !l.trim().is_empty()) {
        let cells: Vec<&str> = line.split(',').map(str::trim).collect();
        let number = |k: usize| cells.get(k).and_then(|c| c.parse::<f64>().ok()).filter(|v| v.is_finite());
        let bad = || FigureError::Csv(format!("{}:{}: expected disturbance,level,controller,success", path.display(), i + 1));
        let (Some(level), Some(success)) = (number(1), number(3)) else { return Err(bad()) };
        rows.push(RobustnessRow { disturbance: cells[0].to_string(), level, controller: cells[2].to_string(), success });
    }
    if rows.is_empty() {
        return Err(FigureError::Nothing("no robustness rows to draw"));
    }
    Ok(rows)
}

/// Success (%) against level, one panel per disturbance (in the order they first appear), a
/// line per controller.
pub fn draw_robustness(rows: &[RobustnessRow], out: &Path) -> Result<(), FigureError> {
    crate::plot::register_font();
    let mut order: Vec<&str> = Vec::new();
    for r in rows {
        if !order.contains(&r.disturbance.as_str()) {
            order.push(&r.disturbance);
        }
    }
    let columns = 2;
    let grid = (order.len().div_ceil(columns), columns);
    let root = BitMapBackend::new(out, (960, 360 * grid.0 as u32)).into_drawing_area();
    root.fill(&WHITE)?;
    let controllers: Vec<&str> = rows.iter().map(|r| r.controller.as_str()).fold(Vec::new(), |mut v, c| {
        if !v.contains(&c) {
            v.push(c);
        }
        v
    });
    for (panel, disturbance) in root.split_evenly(grid).iter().zip(&order) {
        let mine: Vec<&RobustnessRow> = rows.iter().filter(|r| r.disturbance == *disturbance).collect();
        let max_level = mine.iter().map(|r| r.level).fold(0.0, f64::max).max(1e-9);
        let mut chart = ChartBuilder::on(panel)
            .caption(*disturbance, ("sans-serif", 20))
            .margin(10)
            .x_label_area_size(36)
            .y_label_area_size(50)
            .build_cartesian_2d(0.0..max_level * 1.05, 0.0..100.0)?;
        chart.configure_mesh().x_desc("level").y_desc("success (%)").draw()?;
        for (i, controller) in controllers.iter().enumerate() {
            let points: BTreeMap<u64, f64> =
                mine.iter().filter(|r| r.controller == *controller).map(|r| (r.level.to_bits(), 100.0 * r.success)).collect();
            let mut line: Vec<(f64, f64)> = points.into_iter().map(|(l, s)| (f64::from_bits(l), s)).collect();
            line.sort_by(|a, b| a.0.total_cmp(&b.0));
            let colour = Palette99::pick(i).to_rgba();
            chart
                .draw_series(LineSeries::new(line.iter().copied(), colour.stroke_width(2)).point_size(4))?
                .label(controller.to_string())
                .legend(move |(x, y)| PathElement::new(vec![(x, y), (x + 20, y)], colour.stroke_width(2)));
        }
        chart
            .configure_series_labels()
            .background_style(WHITE.mix(0.8))
            .border_style(BLACK)
            .position(SeriesLabelPosition::LowerLeft)
            .draw()?;
    }
    root.present().map_err(|e| FigureError::Draw(format!("writing {}: {e}", out.display())))?;
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_table_is_read_and_drawn_and_a_bad_row_is_named() {
        let dir = tempfile::tempdir().unwrap();
        let csv = dir.path().join("r.csv");
        std::fs::write(&csv, "disturbance,level,controller,success,s_pw\nwind (m/s),0,pilot,0.84,0.09\nwind (m/s),3,pilot,0.7,0.08\nwind (m/s),0,generalist,0.89,0.15\n").unwrap();
        let rows = read_rows(&csv).unwrap();
        assert_eq!(rows.len(), 3);
        assert_eq!(rows[1], RobustnessRow { disturbance: "wind (m/s)".into(), level: 3.0, controller: "pilot".into(), success: 0.7 });
        let png = dir.path().join("r.png");
        draw_robustness(&rows, &png).unwrap();
        assert_eq!(&std::fs::read(&png).unwrap()[1..4], b"PNG");
        std::fs::write(&csv, "h\nwind,x,pilot,0.5\n").unwrap();
        assert!(read_rows(&csv).unwrap_err().to_string().contains("r.csv:2"));
    }
}
