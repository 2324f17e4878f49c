//! Small line charts (graph size and matching score per session) rendered to RGB pixels.
//!
//! Drawing goes through `embedded-graphics` (lines, rectangles and a built-in bitmap font, so no font file
//! is needed at run time) onto an in-memory RGB buffer, which [`crate::map_image::write_rgb_png`] encodes.

use std::convert::Infallible;

use embedded_graphics::Drawable as _;
use embedded_graphics::mono_font::MonoTextStyle;
use embedded_graphics::mono_font::ascii::FONT_6X10;
use embedded_graphics::pixelcolor::Rgb888;
use embedded_graphics::prelude::{
    DrawTarget, OriginDimensions, Pixel, Point, Primitive as _, RgbColor as _, Size,
};
use embedded_graphics::primitives::{Line, PrimitiveStyle, Rectangle};
use embedded_graphics::text::{Alignment, Text};

/// One curve of a chart.
#[derive(Clone, Debug)]
pub struct Series {
    /// Legend text.
    pub name: String,
    /// Line colour (RGB).
    pub color: [u8; 3],
    /// Points `(x, y)`; non-finite ones are skipped.
    pub points: Vec<(f64, f64)>,
}

/// A chart: title, axis labels and curves sharing one y axis.
#[derive(Clone, Debug)]
pub struct LineChart {
    /// Title at the top.
    pub title: String,
    /// Label of the x axis.
    pub x_label: String,
    /// Label of the y axis.
    pub y_label: String,
    /// The curves.
    pub series: Vec<Series>,
    /// Lower end of the y axis; `None` = the data's minimum (or 0 if all data are positive).
    pub y_min: Option<f64>,
}

/// RGB pixels, row-major.
struct Canvas {
    width: u32,
    height: u32,
    pixels: Vec<u8>,
}

impl OriginDimensions for Canvas {
    fn size(&self) -> Size {
        Size::new(self.width, self.height)
    }
}

impl DrawTarget for Canvas {
    type Color = Rgb888;
    type Error = Infallible;

    fn draw_iter<I>(&mut self, pixels: I) -> Result<(), Self::Error>
    where
        I: IntoIterator<Item = Pixel<Self::Color>>,
    {
        for Pixel(p, c) in pixels {
            if p.x >= 0 && p.y >= 0 && (p.x as u32) < self.width && (p.y as u32) < self.height {
                let i = 3 * (p.y as usize * self.width as usize + p.x as usize);
                self.pixels[i..i + 3].copy_from_slice(&[c.r(), c.g(), c.b()]);
            }
        }
        Ok(())
    }
}

/// A "nice" tick step near `span / 5`.
fn tick_step(span: f64) -> f64 {
    let raw = (span / 5.0).max(f64::MIN_POSITIVE);
    let magnitude = 10f64.powf(raw.log10().floor());
    [1.0, 2.0, 5.0, 10.0]
        .iter()
        .map(|m| m * magnitude)
        .find(|s| *s >= raw)
        .unwrap_or(10.0 * magnitude)
}

fn label(value: f64) -> String {
    if value.abs() >= 1000.0 || value.fract().abs() < 1e-9 {
        format!("{value:.0}")
    } else {
        format!("{value:.2}")
    }
}

impl LineChart {
    /// Renders the chart; returns `(width, height, rgb pixels)`.
    pub fn render(&self, width: u32, height: u32) -> (u32, u32, Vec<u8>) {
        let mut canvas = Canvas {
            width,
            height,
            pixels: vec![255; 3 * width as usize * height as usize],
        };
        let _ = self.draw(&mut canvas);
        (width, height, canvas.pixels)
    }

    fn draw(&self, canvas: &mut Canvas) -> Result<(), Infallible> {
        let (w, h) = (canvas.width as i32, canvas.height as i32);
        let black = Rgb888::BLACK;
        let grey = Rgb888::new(210, 210, 210);
        let text = MonoTextStyle::new(&FONT_6X10, black);
        let (left, right, top, bottom) = (64, w - 16, 28, h - 40);

        let points = || self.series.iter().flat_map(|s| s.points.iter());
        let finite = |p: &&(f64, f64)| p.0.is_finite() && p.1.is_finite();
        let (mut x0, mut x1, mut y0, mut y1) = (f64::MAX, f64::MIN, f64::MAX, f64::MIN);
        for &(x, y) in points().filter(finite) {
            x0 = x0.min(x);
            x1 = x1.max(x);
            y0 = y0.min(y);
            y1 = y1.max(y);
        }
        if x0 > x1 {
            (x0, x1, y0, y1) = (0.0, 1.0, 0.0, 1.0);
        }
        y0 = self.y_min.unwrap_or(if y0 >= 0.0 { 0.0 } else { y0 });
        if y1 <= y0 {
            y1 = y0 + 1.0;
        }
        if x1 <= x0 {
            x1 = x0 + 1.0;
        }
        let y_step = tick_step(y1 - y0);
        y1 = (y1 / y_step).ceil() * y_step;
        let to_px = |x: f64, y: f64| {
            Point::new(
                left + ((x - x0) / (x1 - x0) * f64::from(right - left)).round() as i32,
                bottom - ((y - y0) / (y1 - y0) * f64::from(bottom - top)).round() as i32,
            )
        };

        // Grid, ticks and labels.
        let mut y = (y0 / y_step).ceil() * y_step;
        while y <= y1 + 1e-9 {
            let p = to_px(x0, y);
            Line::new(Point::new(left, p.y), Point::new(right, p.y))
                .into_styled(PrimitiveStyle::with_stroke(grey, 1))
                .draw(canvas)?;
            Text::with_alignment(
                &label(y),
                Point::new(left - 4, p.y + 3),
                text,
                Alignment::Right,
            )
            .draw(canvas)?;
            y += y_step;
        }
        let x_step = tick_step(x1 - x0).max(if x1 - x0 >= 5.0 { 1.0 } else { 0.0 });
        let mut x = (x0 / x_step).ceil() * x_step;
        while x <= x1 + 1e-9 {
            let p = to_px(x, y0);
            Line::new(Point::new(p.x, bottom), Point::new(p.x, bottom + 4))
                .into_styled(PrimitiveStyle::with_stroke(black, 1))
                .draw(canvas)?;
            Text::with_alignment(
                &label(x),
                Point::new(p.x, bottom + 14),
                text,
                Alignment::Center,
            )
            .draw(canvas)?;
            x += x_step;
        }
        Rectangle::with_corners(Point::new(left, top), Point::new(right, bottom))
            .into_styled(PrimitiveStyle::with_stroke(black, 1))
            .draw(canvas)?;
        Text::with_alignment(&self.title, Point::new(w / 2, 14), text, Alignment::Center)
            .draw(canvas)?;
        Text::with_alignment(
            &self.x_label,
            Point::new(i32::midpoint(left, right), h - 8),
            text,
            Alignment::Center,
        )
        .draw(canvas)?;
        Text::new(&self.y_label, Point::new(4, top - 6), text).draw(canvas)?;

        // Curves and legend.
        for (k, series) in self.series.iter().enumerate() {
            let color = Rgb888::new(series.color[0], series.color[1], series.color[2]);
            let style = PrimitiveStyle::with_stroke(color, 2);
            let pts: Vec<Point> = series
                .points
                .iter()
                .filter(|p| p.0.is_finite() && p.1.is_finite())
                .map(|&(x, y)| to_px(x, y))
                .collect();
            for pair in pts.windows(2) {
                Line::new(pair[0], pair[1])
                    .into_styled(style)
                    .draw(canvas)?;
            }
            for p in &pts {
                Rectangle::new(*p - Point::new(2, 2), Size::new(5, 5))
                    .into_styled(PrimitiveStyle::with_fill(color))
                    .draw(canvas)?;
            }
            let ly = top + 12 + 14 * k as i32;
            Line::new(Point::new(left + 8, ly - 3), Point::new(left + 24, ly - 3))
                .into_styled(style)
                .draw(canvas)?;
            Text::new(&series.name, Point::new(left + 28, ly), text).draw(canvas)?;
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn draws_curves_in_their_colours() {
        let chart = LineChart {
            title: "t".into(),
            x_label: "session".into(),
            y_label: "count".into(),
            series: vec![Series {
                name: "nodes".into(),
                color: [200, 0, 0],
                points: vec![(0.0, 1.0), (1.0, 3.0), (2.0, f64::NAN), (3.0, 2.0)],
            }],
            y_min: None,
        };
        let (w, h, px) = chart.render(320, 200);
        assert_eq!(px.len(), 3 * w as usize * h as usize);
        let red = px.chunks(3).filter(|c| c == &[200, 0, 0]).count();
        assert!(red > 100, "{red} red pixels");
        // Nothing is drawn for an empty chart but the frame: still a valid image.
        let empty = LineChart {
            series: Vec::new(),
            ..chart
        };
        let (_, _, px) = empty.render(100, 80);
        assert!(px.contains(&0));
    }

    #[test]
    fn tick_steps_are_round() {
        assert!((tick_step(10.0) - 2.0).abs() < 1e-12);
        assert!((tick_step(0.37) - 0.1).abs() < 1e-12);
        assert!((tick_step(4500.0) - 1000.0).abs() < 1e-9);
    }
}
