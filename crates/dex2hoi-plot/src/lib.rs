//! Pictures without a graphics stack: a 3 x 5 bitmap font ([`font`]), line charts of one or
//! more panels ([`chart`]: the loss curves of a training run, metrics against training steps)
//! and the 8-bit RGB PNG encoder they and the motion preview write with ([`encode_rgb_png`]).

pub mod chart;
pub mod font;

/// A picture that could not be encoded.
#[derive(Debug, thiserror::Error)]
#[error("PNG encoding: {0}")]
pub struct PlotError(#[from] png::EncodingError);

/// Shorthand for `Result<T, PlotError>`.
pub type Result<T, E = PlotError> = std::result::Result<T, E>;

/// An 8-bit RGB PNG of `rgb` (rows top to bottom, three bytes a pixel), `width` x `height`.
pub fn encode_rgb_png(width: u32, height: u32, rgb: &[u8]) -> Result<Vec<u8>> {
    let mut bytes = Vec::new();
    {
        let mut encoder = png::Encoder::new(&mut bytes, width, height);
        encoder.set_color(png::ColorType::Rgb);
        encoder.set_depth(png::BitDepth::Eight);
        let mut writer = encoder.write_header()?;
        writer.write_image_data(rgb)?;
        writer.finish()?;
    }
    Ok(bytes)
}
