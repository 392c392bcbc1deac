//! Line charts: the PNG's size follows the panels and the legend, every series is drawn in its
//! colour and the reference line in grey, where the points say; gaps (NaN, non-positive values
//! on a log axis), flat series and empty panels draw without failing.

use dex2hoi_plot::chart::{Chart, PALETTE, Panel, Scale, Series};

fn decode(bytes: &[u8]) -> (usize, usize, Vec<[u8; 3]>) {
    let decoder = png::Decoder::new(std::io::Cursor::new(bytes));
    let mut reader = decoder.read_info().unwrap();
    let mut buffer = vec![0; reader.output_buffer_size().unwrap()];
    let info = reader.next_frame(&mut buffer).unwrap();
    assert_eq!(info.color_type, png::ColorType::Rgb);
    let pixels = buffer[..info.buffer_size()].chunks(3).map(|c| [c[0], c[1], c[2]]).collect();
    (info.width as usize, info.height as usize, pixels)
}

fn count(pixels: &[[u8; 3]], colour: [u8; 3]) -> usize {
    pixels.iter().filter(|&&p| p == colour).count()
}

fn series(label: &str, points: &[(f64, f64)]) -> Series {
    Series { label: label.into(), points: points.to_vec() }
}

#[test]
fn two_series_and_a_reference_are_drawn_in_their_colours() {
    let rising = series("a", &[(1000.0, 1.0), (2000.0, 2.0), (3000.0, 3.0)]);
    let falling = series("b", &[(1000.0, 3.0), (3000.0, 1.0)]);
    let chart = Chart {
        panels: vec![Panel {
            title: "metric".into(),
            series: vec![rising, falling],
            reference: Some(2.5),
            scale: Scale::Linear,
        }],
        columns: 1,
        legend: vec!["a".into(), "b".into()],
    };
    let (width, height, pixels) = decode(&chart.encode_png().unwrap());
    let (one_width, one_height) = (width, height);
    assert!(count(&pixels, PALETTE[0]) > 100 && count(&pixels, PALETTE[1]) > 100);
    assert!(count(&pixels, [120, 120, 120]) > 50, "the dashed reference");

    // The rising series: its leftmost pixel below its rightmost one (image y grows downwards).
    let rows = |colour: [u8; 3], leftmost: bool| {
        let mut found: Option<(usize, usize)> = None;
        // Skip the legend band at the top, which holds a sample of each colour.
        for (index, &p) in pixels.iter().enumerate().skip(width * 30) {
            let (x, y) = (index % width, index / width);
            if p == colour && found.is_none_or(|(fx, _)| if leftmost { x < fx } else { x > fx }) {
                found = Some((x, y));
            }
        }
        found.unwrap()
    };
    assert!(rows(PALETTE[0], true).1 > rows(PALETTE[0], false).1, "series a rises");
    assert!(rows(PALETTE[1], true).1 < rows(PALETTE[1], false).1, "series b falls");

    // Four panels in three columns: two rows; without a legend, no legend band.
    let panel = |title: &str, points: &[(f64, f64)], scale| Panel {
        title: title.into(),
        series: vec![series("only", points)],
        reference: None,
        scale,
    };
    let chart = Chart {
        panels: vec![
            panel("gaps", &[(0.0, 1.0), (1.0, f64::NAN), (2.0, 3.0)], Scale::Linear),
            panel("log with zero", &[(0.0, 0.0), (1.0, 10.0), (2.0, 100.0)], Scale::Log),
            panel("flat", &[(0.0, 5.0), (1.0, 5.0)], Scale::Linear),
            panel("empty", &[], Scale::Linear),
        ],
        columns: 3,
        legend: Vec::new(),
    };
    let (width, height, pixels) = decode(&chart.encode_png().unwrap());
    assert_eq!(width, 3 * one_width);
    assert!(height > one_height, "two rows of panels: {height} against {one_height}");
    assert!(count(&pixels, PALETTE[0]) > 100, "the drawable points are drawn");
    let again = chart.encode_png().unwrap();
    assert_eq!(decode(&again).2, pixels, "deterministic");
}
