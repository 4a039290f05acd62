// The size of an image file's pixels as stored, which is what the search decodes.

/**
 * A JPEG's stored [width, height], read from its frame header (SOF); null for anything else.
 * Browsers report a JPEG's size turned by its EXIF Orientation, even when it is drawn as
 * stored (Chromium's naturalWidth does), while the controller decodes the stored pixels.
 * Markers are walked by their segment lengths: EXIF and ICC segments come before the frame.
 */
export async function storedJpegSize(blob) {
  const bytes = new Uint8Array(await blob.arrayBuffer());
  if (bytes[0] !== 0xff || bytes[1] !== 0xd8) return null;
  let at = 2;
  while (at + 4 <= bytes.length) {
    if (bytes[at] !== 0xff) return null;
    const marker = bytes[at + 1];
    if (marker === 0xff) {
      at += 1; // a fill byte before the marker
      continue;
    }
    if (marker === 0xd9 || marker === 0xda) return null; // the image ended or its scan began
    const frame = marker >= 0xc0 && marker <= 0xcf && marker !== 0xc4 && marker !== 0xc8 && marker !== 0xcc;
    if (frame && at + 9 <= bytes.length) return [(bytes[at + 7] << 8) | bytes[at + 8], (bytes[at + 5] << 8) | bytes[at + 6]];
    at += 2 + ((bytes[at + 2] << 8) | bytes[at + 3]);
  }
  return null;
}
