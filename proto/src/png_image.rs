//! The one PNG encoder: [`mapping::map_image`]'s pixel buffers as PNG bytes, for the agent's picture
//! files, the server's `GetMapImage` reply ([`crate::pb::MapImage`] carries a PNG) and the web console's
//! images.
//!
//! It lives here, not beside the pixels in `mapping`, because `mapping` stays free of image-format
//! dependencies, and this is the crate both the agent and the server link (neither links the other).
//! Bytes out, no I/O.

/// How the pixels are laid out: 8 bits per channel, one pixel per cell, top row first.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum PngPixels {
    /// One byte per pixel.
    Gray,
    /// Three bytes per pixel: red, green, blue.
    Rgb,
}

/// How hard the encoder compresses.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub enum PngCompression {
    /// The encoder's default: files to keep and the `GetMapImage` reply.
    #[default]
    Balanced,
    /// fdeflate: a few milliseconds for the README demo's 1000 × 700 map, about as small as
    /// [`Self::Balanced`] (the web console, which encodes an image per version).
    Fast,
}

/// Why an image could not be encoded.
#[derive(Debug, thiserror::Error)]
pub enum PngError {
    /// No pixels: zero width or height.
    #[error("the image is empty")]
    Empty,
    /// The encoder refused (e.g. a buffer whose size does not match the dimensions).
    #[error(transparent)]
    Encoding(#[from] png::EncodingError),
}

/// `pixels` (`width` × `height`, laid out as `layout` says) as PNG bytes, compressed as `compression`
/// says.
pub fn encode_png(
    width: u32,
    height: u32,
    layout: PngPixels,
    pixels: &[u8],
    compression: PngCompression,
) -> Result<Vec<u8>, PngError> {
    if width == 0 || height == 0 {
        return Err(PngError::Empty);
    }
    let mut png = Vec::new();
    let mut encoder = png::Encoder::new(&mut png, width, height);
    encoder.set_color(match layout {
        PngPixels::Gray => png::ColorType::Grayscale,
        PngPixels::Rgb => png::ColorType::Rgb,
    });
    encoder.set_depth(png::BitDepth::Eight);
    encoder.set_compression(match compression {
        PngCompression::Balanced => png::Compression::Balanced,
        PngCompression::Fast => png::Compression::Fast,
    });
    let mut writer = encoder.write_header()?;
    writer.write_image_data(pixels)?;
    writer.finish()?;
    Ok(png)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn gray_and_rgb_pixels_decode_back() {
        for (layout, channels) in [(PngPixels::Gray, 1), (PngPixels::Rgb, 3)] {
            for compression in [PngCompression::Balanced, PngCompression::Fast] {
                let pixels: Vec<u8> = (0..3 * 2 * channels).map(|i| (i * 37) as u8).collect();
                let bytes = encode_png(3, 2, layout, &pixels, compression).unwrap();
                let decoder = png::Decoder::new(std::io::Cursor::new(&bytes));
                let mut reader = decoder.read_info().unwrap();
                let mut back = vec![0; reader.output_buffer_size().unwrap()];
                let info = reader.next_frame(&mut back).unwrap();
                assert_eq!((info.width, info.height), (3, 2));
                assert_eq!(&back[..info.buffer_size()], &pixels[..]);
            }
        }
    }

    #[test]
    fn an_empty_or_short_buffer_is_refused() {
        let empty = encode_png(0, 4, PngPixels::Gray, &[], PngCompression::Balanced);
        assert!(matches!(empty, Err(PngError::Empty)));
        let short = encode_png(2, 2, PngPixels::Rgb, &[0; 5], PngCompression::Balanced);
        assert!(matches!(short, Err(PngError::Encoding(_))));
    }
}
