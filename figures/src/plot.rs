//! Drawings: tracks (per track a top view (x–y) and a side view (x–z) with the arena, the gates
//! as oriented bars with index and direction, the start pose and the reference pilot's line),
//! experiments' validation curves, and single runs' learning curves.

use std::path::Path;
use std::sync::{Arc, Once};

use plotters::coord::Shift;
use plotters::prelude::*;
use sim::nalgebra::Vector3;
use sim::{ReferencePilot, Track};

use crate::FigureError;

/// How tracks are laid out.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Layout {
    /// Top view above side view, 480 px wide cells.
    TopAndSide,
    /// Top view only, 320 px wide cells: a gallery of many tracks.
    Gallery,
}

impl Layout {
    fn cell_width(self) -> u32 {
        match self {
            Layout::TopAndSide => 480,
            Layout::Gallery => 320,
        }
    }

    fn cell_height(self) -> u32 {
        let w = self.cell_width();
        match self {
            Layout::TopAndSide => w + (w as f64 * SIDE_VIEW_FRACTION) as u32 + 30,
            Layout::Gallery => w + 30,
        }
    }
}
/// Height of the side view, as a fraction of the cell width.
const SIDE_VIEW_FRACTION: f64 = 0.42;

const GATE: RGBColor = RGBColor(200, 40, 40);
const LINE: RGBColor = RGBColor(120, 160, 220);
const START: RGBColor = RGBColor(20, 140, 60);
const ARENA: RGBColor = RGBColor(90, 90, 90);

/// Draws every track into one PNG, in a grid of about square shape.
pub fn draw_tracks(tracks: &[Arc<Track>], out: &Path, layout: Layout) -> Result<(), FigureError> {
    if tracks.is_empty() {
        return Err(FigureError::Nothing("no tracks to draw"));
    }
    register_font();
    let cols = (tracks.len() as f64).sqrt().ceil() as u32;
    let rows = (tracks.len() as u32).div_ceil(cols);
    if let Some(parent) = out.parent().filter(|p| !p.as_os_str().is_empty()) {
        std::fs::create_dir_all(parent).map_err(|source| FigureError::Io { what: format!("creating {}", parent.display()), source })?;
    }
    let root = BitMapBackend::new(out, (cols * layout.cell_width(), rows * layout.cell_height())).into_drawing_area();
    root.fill(&WHITE)?;
    for (area, track) in root.split_evenly((rows as usize, cols as usize)).iter().zip(tracks) {
        draw_track(area, track, layout).map_err(|e| FigureError::Draw(format!("drawing {}: {e}", track.name)))?;
    }
    root.present().map_err(|e| FigureError::Draw(format!("writing {}: {e}", out.display())))?;
    Ok(())
}

/// The font is compiled in, so drawings look the same on every machine.
pub(crate) fn register_font() {
    static ONCE: Once = Once::new();
    ONCE.call_once(|| {
        plotters::style::register_font("sans-serif", FontStyle::Normal, epaint_default_fonts::UBUNTU_LIGHT)
            .unwrap_or_else(|_| panic!("the bundled font is a valid TrueType font"));
    });
}

/// Which world axes a view shows.
#[derive(Clone, Copy)]
enum View {
    Top,
    Side,
}

impl View {
    fn project(self, p: &Vector3<f64>) -> (f64, f64) {
        match self {
            View::Top => (p.x, p.y),
            View::Side => (p.x, p.z),
        }
    }
}

fn draw_track(area: &DrawingArea<BitMapBackend<'_>, Shift>, track: &Track, layout: Layout) -> Result<(), FigureError> {
    let title = format!("{} ({} gates)", track.name, track.gates.len());
    let area = area.margin(8, 0, 0, 0).titled(&title, ("sans-serif", 18))?;
    let line = ReferencePilot::default().racing_line(track);
    match layout {
        Layout::TopAndSide => {
            let side_height = (layout.cell_width() as f64 * SIDE_VIEW_FRACTION) as u32;
            let (top, side) = area.split_vertically(area.dim_in_pixel().1 - side_height);
            draw_view(&top, track, &line, View::Top)?;
            draw_view(&side, track, &line, View::Side)?;
        }
        Layout::Gallery => draw_view(&area, track, &line, View::Top)?,
    }
    Ok(())
}

fn draw_view(area: &DrawingArea<BitMapBackend<'_>, Shift>, track: &Track, line: &[Vector3<f64>], view: View) -> Result<(), FigureError> {
    let (lo, hi) = (view.project(&track.arena.min), view.project(&track.arena.max));
    let pad = 0.5;
    let (y_label, x_label) = match view {
        View::Top => ("y (m)", "x (m)"),
        View::Side => ("z (m)", "x (m)"),
    };
    let mut chart = ChartBuilder::on(area)
        .margin(6)
        .x_label_area_size(28)
        .y_label_area_size(36)
        .build_cartesian_2d((lo.0 - pad)..(hi.0 + pad), (lo.1 - pad)..(hi.1 + pad))?;
    chart
        .configure_mesh()
        .light_line_style(WHITE.mix(0.0))
        .bold_line_style(BLACK.mix(0.08))
        .x_desc(x_label)
        .y_desc(y_label)
        .label_style(("sans-serif", 12))
        .draw()?;
    // Arena.
    chart.draw_series(std::iter::once(Rectangle::new([lo, hi], ARENA.stroke_width(2))))?;
    // Racing line of the reference pilot.
    let mut closed: Vec<(f64, f64)> = line.iter().map(|p| view.project(p)).collect();
    closed.extend(closed.first().copied());
    chart.draw_series(std::iter::once(PathElement::new(closed, LINE.stroke_width(1))))?;
    // Gates: the outer frame as a bar, an arrow along the flight direction, the index.
    for (i, gate) in track.gates.iter().enumerate() {
        let outer = match view {
            // Seen from above the frame is a 2 m bar across the flight direction.
            View::Top => [Vector3::new(0.0, -1.0, 0.0), Vector3::new(0.0, 1.0, 0.0)],
            // From the side, its vertical extent at the gate's lateral ends.
            View::Side => [Vector3::new(0.0, 0.0, -1.0), Vector3::new(0.0, 0.0, 1.0)],
        };
        let bar: Vec<(f64, f64)> = outer.iter().map(|l| view.project(&gate.to_world(l))).collect();
        chart.draw_series(std::iter::once(PathElement::new(bar, GATE.stroke_width(4))))?;
        let tip = view.project(&(gate.position + gate.normal() * 1.2));
        let base = view.project(&gate.position);
        chart.draw_series(std::iter::once(PathElement::new(vec![base, tip], GATE.stroke_width(2))))?;
        chart.draw_series(std::iter::once(Circle::new(tip, 3, GATE.filled())))?;
        let label = view.project(&gate.to_world(&Vector3::new(-0.6, 1.3, 1.3)));
        chart.draw_series(std::iter::once(Text::new(i.to_string(), label, ("sans-serif", 15).into_font().color(&BLACK))))?;
    }
    // Start pose: a dot and its heading.
    let start = view.project(&track.start.position);
    let heading = Vector3::new(track.start.yaw.cos(), track.start.yaw.sin(), 0.0);
    let ahead = view.project(&(track.start.position + heading * 1.0));
    chart.draw_series(std::iter::once(Circle::new(start, 5, START.filled())))?;
    chart.draw_series(std::iter::once(PathElement::new(vec![start, ahead], START.stroke_width(2))))?;
    Ok(())
}

/// Validation S_pw against environment steps: per variant a thin line per seed, and the mean
/// over its seeds (bold) with their range as a band where every seed has reached.
pub fn draw_validation_curves(variants: &[runtime::experiment::VariantSummary], out: &Path) -> Result<(), FigureError> {
    register_font();
    let root = BitMapBackend::new(out, (960, 600)).into_drawing_area();
    root.fill(&WHITE)?;
    let points = variants.iter().flat_map(|v| v.curves.iter().flat_map(|(_, c)| c.iter()));
    let (max_steps, max_s_pw) = points.fold((1.0f64, 0.01f64), |(x, y), p| (x.max(p.env_steps as f64 / 1e6), y.max(p.s_pw)));
    let mut chart = ChartBuilder::on(&root)
        .caption("validation S_pw during training", ("sans-serif", 22))
        .margin(12)
        .x_label_area_size(40)
        .y_label_area_size(60)
        .build_cartesian_2d(0.0..max_steps * 1.02, 0.0..max_s_pw * 1.1)?;
    chart.configure_mesh().x_desc("environment steps (millions)").y_desc("S_pw (1/s)").draw()?;
    for (i, variant) in variants.iter().enumerate() {
        let colour = Palette99::pick(i).to_rgba();
        // Seeds are evaluated at the same iterations, so their points line up by env steps.
        let mut by_steps: std::collections::BTreeMap<u64, Vec<f64>> = Default::default();
        for (_, curve) in &variant.curves {
            for p in curve {
                by_steps.entry(p.env_steps).or_default().push(p.s_pw);
            }
        }
        for (_, curve) in &variant.curves {
            let line = curve.iter().map(|p| (p.env_steps as f64 / 1e6, p.s_pw));
            chart.draw_series(LineSeries::new(line, colour.mix(0.45).stroke_width(1)))?;
        }
        let seeds = variant.curves.len();
        let rows: Vec<(f64, f64, f64, f64)> = by_steps
            .iter()
            .filter(|(_, v)| v.len() == seeds)
            .map(|(x, v)| {
                let lo = v.iter().copied().fold(f64::INFINITY, f64::min);
                let hi = v.iter().copied().fold(f64::NEG_INFINITY, f64::max);
                (*x as f64 / 1e6, v.iter().sum::<f64>() / v.len() as f64, lo, hi)
            })
            .collect();
        if rows.len() < 2 {
            continue;
        }
        let band: Vec<(f64, f64)> = rows.iter().map(|r| (r.0, r.3)).chain(rows.iter().rev().map(|r| (r.0, r.2))).collect();
        chart.draw_series(std::iter::once(Polygon::new(band, colour.mix(0.2).filled())))?;
        chart
            .draw_series(LineSeries::new(rows.iter().map(|r| (r.0, r.1)), colour.stroke_width(2)))?
            .label(format!("{} ({} seed{})", variant.name, seeds, if seeds == 1 { "" } else { "s" }))
            .legend(move |(x, y)| PathElement::new(vec![(x, y), (x + 20, y)], colour.stroke_width(2)));
    }
    chart.configure_series_labels().background_style(WHITE.mix(0.8)).border_style(BLACK).position(SeriesLabelPosition::UpperLeft).draw()?;
    root.present().map_err(|e| FigureError::Draw(format!("writing {}: {e}", out.display())))?;
    Ok(())
}

/// Success per track against environment steps for a sequential curriculum, with a dashed line
/// where each later stage began (thesis Fig. 3.5).
pub fn draw_track_curves(
    curves: &[runtime::experiment::TrackCurve],
    boundaries: &[u64],
    title: &str,
    out: &Path,
) -> Result<(), FigureError> {
    register_font();
    let root = BitMapBackend::new(out, (960, 600)).into_drawing_area();
    root.fill(&WHITE)?;
    let max_steps = curves.iter().flat_map(|c| c.points.iter()).map(|p| p.0 as f64 / 1e6).fold(1.0, f64::max);
    let mut chart = ChartBuilder::on(&root)
        .caption(title, ("sans-serif", 22))
        .margin(12)
        .x_label_area_size(40)
        .y_label_area_size(60)
        .build_cartesian_2d(0.0..max_steps * 1.02, 0.0..1.05)?;
    chart.configure_mesh().x_desc("environment steps since the first stage (millions)").y_desc("validation success").draw()?;
    for &b in boundaries {
        let x = b as f64 / 1e6;
        chart.draw_series(DashedLineSeries::new(vec![(x, 0.0), (x, 1.05)], 6, 4, BLACK.mix(0.5).stroke_width(1)))?;
    }
    for (i, curve) in curves.iter().enumerate() {
        let colour = Palette99::pick(i).to_rgba();
        chart
            .draw_series(LineSeries::new(curve.points.iter().map(|p| (p.0 as f64 / 1e6, p.1)), colour.stroke_width(2)))?
            .label(curve.track.clone())
            .legend(move |(x, y)| PathElement::new(vec![(x, y), (x + 20, y)], colour.stroke_width(2)));
    }
    chart
        .configure_series_labels()
        .background_style(WHITE.mix(0.8))
        .border_style(BLACK)
        .position(SeriesLabelPosition::UpperRight)
        .draw()?;
    root.present().map_err(|e| FigureError::Draw(format!("writing {}: {e}", out.display())))?;
    Ok(())
}

/// One run's learning curves as `metrics.csv` holds them: (env steps, value) per column.
pub struct RunCurves {
    /// The run's name in the legend (its directory).
    pub name: String,
    /// Mean training return of the episodes that ended in each iteration.
    pub training_return: Vec<(f64, f64)>,
    /// Validation S_pw at each validation.
    pub validation_s_pw: Vec<(f64, f64)>,
    /// Validation success at each validation.
    pub validation_success: Vec<(f64, f64)>,
}

impl RunCurves {
    /// Reads `<run>/metrics.csv`; columns are found by their names, so files of older runs
    /// (fewer columns) read too. Empty cells (no episode ended, no validation due) are skipped.
    pub fn read(run: &Path) -> Result<Self, FigureError> {
        let path = run.join("metrics.csv");
        let text =
            std::fs::read_to_string(&path).map_err(|source| FigureError::Io { what: format!("reading {}", path.display()), source })?;
        let mut lines = text.lines();
        let header: Vec<&str> = lines.next().ok_or_else(|| FigureError::Csv(format!("{}: empty", path.display())))?.split(',').collect();
        let column = |name: &str| {
            header.iter().position(|h| *h == name).ok_or_else(|| FigureError::Csv(format!("{}: no column {name}", path.display())))
        };
        let (steps, ret, s_pw, success) =
            (column("env_steps")?, column("charts/episodic_return")?, column("eval/S_pw")?, column("eval/success")?);
        let mut curves = Self {
            name: run.file_name().map_or_else(|| run.display().to_string(), |n| n.to_string_lossy().into_owned()),
            training_return: Vec::new(),
            validation_s_pw: Vec::new(),
            validation_success: Vec::new(),
        };
        for (row, line) in lines.enumerate() {
            let cells: Vec<&str> = line.split(',').collect();
            let number = |i: usize| cells.get(i).and_then(|c| c.parse::<f64>().ok()).filter(|v| v.is_finite());
            let x = number(steps).ok_or_else(|| FigureError::Csv(format!("{}: row {}: no env_steps", path.display(), row + 2)))? / 1e6;
            for (i, series) in
                [(ret, &mut curves.training_return), (s_pw, &mut curves.validation_s_pw), (success, &mut curves.validation_success)]
            {
                if let Some(y) = number(i) {
                    series.push((x, y));
                }
            }
        }
        Ok(curves)
    }
}

/// Training return, validation S_pw and validation success against environment steps, one
/// panel each, every run overlaid in its own colour.
pub fn draw_run_curves(runs: &[RunCurves], out: &Path) -> Result<(), FigureError> {
    register_font();
    let root = BitMapBackend::new(out, (960, 1080)).into_drawing_area();
    root.fill(&WHITE)?;
    let panels = root.split_evenly((3, 1));
    type Pick = fn(&RunCurves) -> &[(f64, f64)];
    let series: [(&str, Pick); 3] = [
        ("training return (mean over the episodes of an iteration)", |r| &r.training_return),
        ("validation S_pw (1/s)", |r| &r.validation_s_pw),
        ("validation success", |r| &r.validation_success),
    ];
    let max_x = runs.iter().flat_map(|r| r.training_return.iter().chain(&r.validation_s_pw)).map(|p| p.0).fold(1.0, f64::max);
    for (panel, (title, pick)) in panels.iter().zip(series) {
        let ys = runs.iter().flat_map(|r| pick(r).iter().map(|p| p.1));
        let (low, high) = ys.fold((0.0f64, 0.0f64), |(lo, hi), y| (lo.min(y), hi.max(y)));
        let pad = ((high - low) * 0.05).max(1e-3);
        let mut chart = ChartBuilder::on(panel)
            .caption(title, ("sans-serif", 20))
            .margin(10)
            .x_label_area_size(36)
            .y_label_area_size(60)
            .build_cartesian_2d(0.0..max_x * 1.02, (low - pad)..(high + pad))?;
        chart.configure_mesh().x_desc("environment steps (millions)").draw()?;
        for (i, run) in runs.iter().enumerate() {
            let colour = Palette99::pick(i).to_rgba();
            chart
                .draw_series(LineSeries::new(pick(run).iter().copied(), colour.stroke_width(2)))?
                .label(run.name.clone())
                .legend(move |(x, y)| PathElement::new(vec![(x, y), (x + 20, y)], colour.stroke_width(2)));
        }
        chart
            .configure_series_labels()
            .background_style(WHITE.mix(0.8))
            .border_style(BLACK)
            .position(SeriesLabelPosition::LowerRight)
            .draw()?;
    }
    root.present().map_err(|e| FigureError::Draw(format!("writing {}: {e}", out.display())))?;
    Ok(())
}
