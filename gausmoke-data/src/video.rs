//! In-process decoding of H.264 video in MP4 files: `mp4` demuxes, the avcC length-prefixed
//! samples become Annex-B access units (SPS/PPS from the avcC box in front of every sync
//! sample), `rusty_h264-decoder` decodes them in decode order, and each picture is put at its
//! **presentation** position, ranked by the container's composition time
//! (`decode time + ctts offset`), so B-frames land where they are shown.
//!
//! Colour: the SPS VUI is parsed here (the decoder does not expose it) for
//! `video_full_range_flag` and `matrix_coefficients`. Limited range ("TV", the H.264 default
//! when the VUI says nothing) maps luma 16..235 and chroma 16..240 to `[0, 1]` and
//! `[-0.5, 0.5]`; full range maps 0..255. YCbCr goes to RGB with the matrix the stream
//! declares (BT.601 when unspecified, as ffmpeg does). Chroma (4:2:0) is replicated over its
//! 2x2 luma block; resampling happens in YCbCr before the clamp (see `YuvTable::convert`).
//!
//! The ScalarReal videos carry no `video_signal_type` in their VUI: the range is not declared,
//! so the H.264 default, limited range, applies, and matrix_coefficients is unspecified
//! (BT.601 used; the frames are grey, so the matrix does not matter). Their black background
//! sits at Y = 17, which confirms limited range (test
//! `scalar_real_videos_are_limited_range_1080x1920_120_frames`).

use std::io::BufReader;
use std::ops::Range;
use std::path::Path;

use rusty_h264_decoder::Decoder;

use crate::error::{DataError, Result, io_err};
use crate::image::{Image, RowResampler};

/// Colour signalling read from the stream's SPS.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct ColourInfo {
    /// `video_full_range_flag` (false, i.e. limited 16-235, when the VUI omits it).
    pub full_range: bool,
    /// Whether the VUI carries `video_signal_type` (range stated explicitly).
    pub range_declared: bool,
    /// `matrix_coefficients` (2 = unspecified when the VUI omits it).
    pub matrix_coefficients: u8,
    pub chroma_format_idc: u32,
    pub bit_depth_luma: u32,
    pub bit_depth_chroma: u32,
}

/// What the container and stream say about a video.
#[derive(Debug, Clone, PartialEq)]
pub struct VideoInfo {
    pub width: u32,
    pub height: u32,
    /// Number of samples (coded pictures) in the video track.
    pub frame_count: usize,
    pub colour: ColourInfo,
}

/// Result of [`decode_mp4`]: the stream's properties and the requested frames in
/// presentation order.
pub struct DecodedVideo {
    pub info: VideoInfo,
    pub frames: Vec<Image>,
}

fn video_err(path: &Path, reason: impl Into<String>) -> DataError {
    DataError::Video {
        path: path.to_path_buf(),
        reason: reason.into(),
    }
}

struct Demuxed {
    width: u32,
    height: u32,
    parameter_sets: Vec<u8>,
    colour: ColourInfo,
    /// (composition time, Annex-B access unit, is_sync) in decode order.
    samples: Vec<(i64, Vec<u8>, bool)>,
}

const START_CODE: [u8; 4] = [0, 0, 0, 1];

fn demux(path: &Path) -> Result<Demuxed> {
    let file = std::fs::File::open(path).map_err(io_err(path))?;
    let size = file.metadata().map_err(io_err(path))?.len();
    // The mp4 crate has a few `expect`s on malformed input; a panic there must not escape as
    // a panic of the loader.
    let read = std::panic::catch_unwind(std::panic::AssertUnwindSafe(|| -> Result<Demuxed> {
        let mut reader = mp4::Mp4Reader::read_header(BufReader::new(file), size)
            .map_err(|e| video_err(path, format!("not a readable MP4 container ({e})")))?;
        let (track_id, avc1) = reader
            .tracks()
            .values()
            .find_map(|t| {
                t.trak
                    .mdia
                    .minf
                    .stbl
                    .stsd
                    .avc1
                    .as_ref()
                    .map(|a| (t.track_id(), a.clone()))
            })
            .ok_or_else(|| {
                let kinds: Vec<String> = reader
                    .tracks()
                    .values()
                    .map(|t| {
                        t.box_type()
                            .map(|b| b.to_string())
                            .unwrap_or_else(|_| "unknown".into())
                    })
                    .collect();
                video_err(
                    path,
                    format!(
                        "no H.264 (avc1) video track; tracks found: [{}]",
                        kinds.join(", ")
                    ),
                )
            })?;
        let avcc = &avc1.avcc;
        let length_size = avcc.length_size_minus_one as usize + 1;
        if ![1, 2, 4].contains(&length_size) {
            return Err(video_err(
                path,
                format!("avcC NAL length size {length_size} is not 1, 2 or 4"),
            ));
        }
        let sps = avcc
            .sequence_parameter_sets
            .first()
            .ok_or_else(|| video_err(path, "avcC box has no SPS"))?;
        let colour = parse_sps_colour(&sps.bytes)
            .map_err(|e| video_err(path, format!("cannot parse the SPS: {e}")))?;
        let mut parameter_sets = Vec::new();
        for nal in avcc
            .sequence_parameter_sets
            .iter()
            .chain(&avcc.picture_parameter_sets)
        {
            parameter_sets.extend_from_slice(&START_CODE);
            parameter_sets.extend_from_slice(&nal.bytes);
        }
        let count = reader
            .sample_count(track_id)
            .map_err(|e| video_err(path, format!("cannot count samples ({e})")))?;
        let mut samples = Vec::with_capacity(count as usize);
        for id in 1..=count {
            let sample = reader
                .read_sample(track_id, id)
                .map_err(|e| video_err(path, format!("cannot read sample {id} ({e})")))?
                .ok_or_else(|| video_err(path, format!("sample {id} of {count} is missing")))?;
            let au = avcc_to_annex_b(&sample.bytes, length_size)
                .map_err(|e| video_err(path, format!("sample {id}: {e}")))?;
            let cts = sample.start_time as i64 + i64::from(sample.rendering_offset);
            samples.push((cts, au, sample.is_sync));
        }
        Ok(Demuxed {
            width: u32::from(avc1.width),
            height: u32::from(avc1.height),
            parameter_sets,
            colour,
            samples,
        })
    }));
    read.unwrap_or_else(|_| Err(video_err(path, "the MP4 demuxer failed on malformed data")))
}

/// Converts one length-prefixed (avcC) sample into Annex-B (start-code) NAL units.
fn avcc_to_annex_b(sample: &[u8], length_size: usize) -> std::result::Result<Vec<u8>, String> {
    let mut out = Vec::with_capacity(sample.len() + 16);
    let mut pos = 0;
    while pos < sample.len() {
        if pos + length_size > sample.len() {
            return Err(format!(
                "truncated NAL length field at byte {pos} of {}",
                sample.len()
            ));
        }
        let len = sample[pos..pos + length_size]
            .iter()
            .fold(0usize, |acc, &b| (acc << 8) | b as usize);
        pos += length_size;
        if len == 0 || pos + len > sample.len() {
            return Err(format!(
                "NAL unit of {len} bytes at byte {pos} overruns the {}-byte sample",
                sample.len()
            ));
        }
        out.extend_from_slice(&START_CODE);
        out.extend_from_slice(&sample[pos..pos + len]);
        pos += len;
    }
    Ok(out)
}

/// Reads the stream's properties (size, frame count, colour signalling) without decoding.
pub fn probe_mp4(path: &Path) -> Result<VideoInfo> {
    let d = demux(path)?;
    Ok(VideoInfo {
        width: d.width,
        height: d.height,
        frame_count: d.samples.len(),
        colour: d.colour,
    })
}

/// Decodes the frames whose presentation index lies in `wanted`, converted to RGB and, when
/// `target` (width, height) is given, area-resampled to it row by row (only the requested
/// resolution is ever held). Decoding stops once every wanted frame is out. Fails when the
/// stream has fewer than `wanted.end` pictures.
pub fn decode_mp4(
    path: &Path,
    wanted: Range<usize>,
    target: Option<(u32, u32)>,
) -> Result<DecodedVideo> {
    let d = demux(path)?;
    let info = VideoInfo {
        width: d.width,
        height: d.height,
        frame_count: d.samples.len(),
        colour: d.colour,
    };
    let c = d.colour;
    if c.chroma_format_idc != 1 || c.bit_depth_luma != 8 || c.bit_depth_chroma != 8 {
        return Err(video_err(
            path,
            format!(
                "only 8-bit 4:2:0 is supported (stream: chroma_format_idc {}, luma {} bit, chroma {} bit)",
                c.chroma_format_idc, c.bit_depth_luma, c.bit_depth_chroma
            ),
        ));
    }
    let matrix = YcbcrMatrix::from_code(c.matrix_coefficients).ok_or_else(|| {
        video_err(
            path,
            format!(
                "unsupported matrix_coefficients {} in the SPS VUI",
                c.matrix_coefficients
            ),
        )
    })?;
    let table = YuvTable::new(c.full_range, matrix);
    if wanted.end > d.samples.len() {
        return Err(video_err(
            path,
            format!(
                "frames {wanted:?} requested, the video track has {} samples",
                d.samples.len()
            ),
        ));
    }
    // Presentation rank of every sample, by composition time (ties: decode order).
    let mut order: Vec<usize> = (0..d.samples.len()).collect();
    order.sort_by_key(|&i| (d.samples[i].0, i));
    let mut rank = vec![0usize; d.samples.len()];
    for (r, &i) in order.iter().enumerate() {
        rank[i] = r;
    }
    let last_needed = order[wanted.clone()].iter().copied().max();

    let mut decoder = Decoder::new();
    let mut slots: Vec<Option<Image>> = vec![None; wanted.len()];
    let mut au_buf = Vec::new();
    if let Some(last_needed) = last_needed {
        for (i, (_, au, is_sync)) in d.samples.iter().enumerate().take(last_needed + 1) {
            au_buf.clear();
            if *is_sync || i == 0 {
                au_buf.extend_from_slice(&d.parameter_sets);
            }
            au_buf.extend_from_slice(au);
            let picture = decoder.decode(&au_buf).map_err(|e| {
                video_err(
                    path,
                    format!(
                        "frame {} (sample {} in decode order) cannot be decoded: {e}; the file \
                         is damaged or uses an unsupported coding tool",
                        rank[i],
                        i + 1
                    ),
                )
            })?;
            // An MP4 sample holds one whole picture, and the decoder returns each picture
            // as its sample completes: none means the slice data ended before the last
            // macroblock, which is damage (a cut or corrupted payload), not a valid stream.
            let Some(picture) = picture else {
                return Err(video_err(
                    path,
                    format!(
                        "frame {} (sample {} in decode order) is damaged: its slice data ends \
                         before the picture is complete",
                        rank[i],
                        i + 1
                    ),
                ));
            };
            if !wanted.contains(&rank[i]) {
                continue;
            }
            let frame_no = rank[i];
            let (w, h) = (picture.width as u32, picture.height as u32);
            if (w, h) != (d.width, d.height) {
                return Err(DataError::FrameSize {
                    path: path.to_path_buf(),
                    frame: frame_no,
                    found_width: w,
                    found_height: h,
                    expected_width: d.width,
                    expected_height: d.height,
                    origin: "the MP4 track header".into(),
                });
            }
            let rgb = table
                .convert(
                    &picture.y,
                    &picture.u,
                    &picture.v,
                    w,
                    h,
                    target.unwrap_or((w, h)),
                )
                .map_err(|e| video_err(path, format!("frame {frame_no}: {e}")))?;
            slots[frame_no - wanted.start] = Some(rgb);
        }
    }
    let decoded = slots.iter().filter(|s| s.is_some()).count();
    let frames: Option<Vec<Image>> = slots.into_iter().collect();
    let frames = frames.ok_or_else(|| {
        video_err(
            path,
            format!(
                "only {decoded} of the {} requested frames {wanted:?} produced a picture",
                wanted.len()
            ),
        )
    })?;
    Ok(DecodedVideo { info, frames })
}

#[derive(Debug, Clone, Copy)]
struct YcbcrMatrix {
    kr: f32,
    kb: f32,
}

impl YcbcrMatrix {
    /// H.264 Table E-5 `matrix_coefficients`.
    fn from_code(code: u8) -> Option<Self> {
        let (kr, kb) = match code {
            1 => (0.2126, 0.0722),       // BT.709
            2 | 5 | 6 => (0.299, 0.114), // unspecified (ffmpeg: BT.601), BT.601
            4 => (0.30, 0.11),           // FCC
            7 => (0.212, 0.087),         // SMPTE 240M
            9 | 10 => (0.2627, 0.0593),  // BT.2020 (non-constant luminance)
            _ => return None,
        };
        Some(Self { kr, kb })
    }
}

/// Look-up tables for 8-bit YCbCr -> RGB.
struct YuvTable {
    y: [f32; 256],
    c: [f32; 256],
    kr: f32,
    kb: f32,
}

impl YuvTable {
    fn new(full_range: bool, m: YcbcrMatrix) -> Self {
        let mut y = [0.0; 256];
        let mut c = [0.0; 256];
        for i in 0..256 {
            let v = i as f32;
            if full_range {
                y[i] = v / 255.0;
                c[i] = (v - 128.0) / 255.0;
            } else {
                y[i] = (v - 16.0) / 219.0;
                c[i] = (v - 128.0) / 224.0;
            }
        }
        Self {
            y,
            c,
            kr: m.kr,
            kb: m.kb,
        }
    }

    /// YCbCr 4:2:0 planes of a `w x h` picture to RGB at `target` size. The planes are
    /// area-resampled in Y'CbCr (chroma from its half-resolution grid, which for the box
    /// filter equals replicating each chroma sample over its 2x2 luma block first), then
    /// converted and clamped to `[0, 1]`, as ffmpeg's scaler orders it. Resampling before the
    /// clamp lets sensor noise below black (Y < 16) average out instead of being rectified.
    fn convert(
        &self,
        py: &[u8],
        pu: &[u8],
        pv: &[u8],
        w: u32,
        h: u32,
        target: (u32, u32),
    ) -> std::result::Result<Image, String> {
        let (wu, hu) = (w as usize, h as usize);
        // The decoder's chroma planes are (width / 2) x (height / 2).
        let (cw, ch) = ((wu / 2).max(1), (hu / 2).max(1));
        if py.len() < wu * hu || pu.len() < cw * ch || pv.len() < cw * ch {
            return Err(format!(
                "decoded planes are too small for {w}x{h} 4:2:0 (Y {}, U {}, V {} bytes)",
                py.len(),
                pu.len(),
                pv.len()
            ));
        }
        let (kr, kb) = (self.kr, self.kb);
        let kg = 1.0 - kr - kb;
        let r_cr = 2.0 * (1.0 - kr);
        let b_cb = 2.0 * (1.0 - kb);
        let g_cb = 2.0 * kb * (1.0 - kb) / kg;
        let g_cr = 2.0 * kr * (1.0 - kr) / kg;
        let (tw, th) = (target.0 as usize, target.1 as usize);
        // Resample Y', Cb, Cr (each mapped to floats first) to the target, then convert.
        let plane = |bytes: &[u8], pw: usize, ph: usize, lut: &[f32; 256]| {
            if pw.is_multiple_of(tw) && ph.is_multiple_of(th) {
                return box_plane(bytes, pw, (pw / tw, ph / th), (tw, th), lut);
            }
            let mut r = RowResampler::new(pw, ph, 1, tw, th);
            let mut row = vec![0.0f32; pw];
            for (j, src) in bytes.chunks_exact(pw).take(ph).enumerate() {
                for (o, &b) in row.iter_mut().zip(src) {
                    *o = lut[b as usize];
                }
                r.push_row(j, &row);
            }
            r.finish()
        };
        let (yp, up, vp) = (
            plane(py, wu, hu, &self.y),
            plane(pu, cw, ch, &self.c),
            plane(pv, cw, ch, &self.c),
        );
        let mut rgb = vec![0.0f32; tw * th * 3];
        for (((px, &yv), &cb), &cr) in rgb.chunks_exact_mut(3).zip(&yp).zip(&up).zip(&vp) {
            px[0] = (yv + r_cr * cr).clamp(0.0, 1.0);
            px[1] = (yv - g_cb * cb - g_cr * cr).clamp(0.0, 1.0);
            px[2] = (yv + b_cb * cb).clamp(0.0, 1.0);
        }
        Image::from_vec(target.0, target.1, rgb).ok_or_else(|| "empty picture".to_string())
    }
}
/// Integer-factor box average of an 8-bit plane (`pitch` bytes per row), summed exactly in
/// integers and mapped through the affine `lut` once per output sample: the same values as
/// the general area filter, at a fraction of the cost. `lut` must be affine in its index
/// (both range tables are), so the mean of mapped values is the mapped mean.
fn box_plane(
    bytes: &[u8],
    pitch: usize,
    factor: (usize, usize),
    out_size: (usize, usize),
    lut: &[f32; 256],
) -> Vec<f32> {
    let (fx, fy) = factor;
    let (tw, th) = out_size;
    let (base, slope) = (lut[0], lut[1] - lut[0]);
    let inv_n = 1.0 / (fx * fy) as f32;
    let mut acc = vec![0u32; tw];
    let mut out = Vec::with_capacity(tw * th);
    for i in 0..th {
        acc.fill(0);
        for r in 0..fy {
            let start = (i * fy + r) * pitch;
            let row = &bytes[start..start + tw * fx];
            for (a, block) in acc.iter_mut().zip(row.chunks_exact(fx)) {
                let mut sum = 0u32;
                for &b in block {
                    sum += u32::from(b);
                }
                *a += sum;
            }
        }
        out.extend(acc.iter().map(|&a| base + slope * (a as f32 * inv_n)));
    }
    out
}

/// Exp-Golomb bit reader over an RBSP (emulation-prevention bytes removed).
struct Bits {
    data: Vec<u8>,
    pos: usize,
}

impl Bits {
    fn new(nal_payload: &[u8]) -> Self {
        let mut data = Vec::with_capacity(nal_payload.len());
        let mut zeros = 0;
        for &b in nal_payload {
            if zeros >= 2 && b == 3 {
                zeros = 0;
                continue;
            }
            zeros = if b == 0 { zeros + 1 } else { 0 };
            data.push(b);
        }
        Self { data, pos: 0 }
    }

    fn bit(&mut self) -> std::result::Result<u32, String> {
        let byte = self
            .data
            .get(self.pos / 8)
            .ok_or_else(|| "SPS ends early".to_string())?;
        let b = (byte >> (7 - self.pos % 8)) & 1;
        self.pos += 1;
        Ok(u32::from(b))
    }

    fn bits(&mut self, n: u32) -> std::result::Result<u32, String> {
        (0..n).try_fold(0u32, |acc, _| Ok((acc << 1) | self.bit()?))
    }

    fn flag(&mut self) -> std::result::Result<bool, String> {
        Ok(self.bit()? == 1)
    }

    fn ue(&mut self) -> std::result::Result<u32, String> {
        let mut zeros = 0;
        while self.bit()? == 0 {
            zeros += 1;
            if zeros > 31 {
                return Err("Exp-Golomb code longer than 32 bits".into());
            }
        }
        Ok(((1u64 << zeros) - 1 + u64::from(self.bits(zeros)?)) as u32)
    }

    fn se(&mut self) -> std::result::Result<i32, String> {
        let k = i64::from(self.ue()?);
        Ok(if k % 2 == 1 { (k + 1) / 2 } else { -(k / 2) } as i32)
    }
}

/// Parses an SPS NAL unit (header byte included) up to the VUI's colour fields
/// (H.264 7.3.2.1.1 and E.1.1).
pub(crate) fn parse_sps_colour(nal: &[u8]) -> std::result::Result<ColourInfo, String> {
    if nal.is_empty() || nal[0] & 0x1f != 7 {
        return Err("the first parameter set is not an SPS NAL unit".into());
    }
    let mut r = Bits::new(&nal[1..]);
    let profile_idc = r.bits(8)?;
    let _constraints = r.bits(8)?;
    let _level = r.bits(8)?;
    let _sps_id = r.ue()?;
    let (mut chroma_format_idc, mut bit_depth_luma, mut bit_depth_chroma) = (1, 8, 8);
    if [100, 110, 122, 244, 44, 83, 86, 118, 128, 138, 139, 134, 135].contains(&profile_idc) {
        chroma_format_idc = r.ue()?;
        if chroma_format_idc == 3 {
            let _separate_colour_plane = r.flag()?;
        }
        bit_depth_luma = r.ue()? + 8;
        bit_depth_chroma = r.ue()? + 8;
        let _qpprime_y_zero_transform_bypass = r.flag()?;
        if r.flag()? {
            let lists = if chroma_format_idc == 3 { 12 } else { 8 };
            for i in 0..lists {
                if r.flag()? {
                    let size = if i < 6 { 16 } else { 64 };
                    let (mut last, mut next) = (8i32, 8i32);
                    for _ in 0..size {
                        if next != 0 {
                            next = (last + r.se()? + 256).rem_euclid(256);
                        }
                        if next != 0 {
                            last = next;
                        }
                    }
                }
            }
        }
    }
    let _log2_max_frame_num = r.ue()?;
    match r.ue()? {
        0 => {
            let _log2_max_poc_lsb = r.ue()?;
        }
        1 => {
            let _delta_always_zero = r.flag()?;
            let _offset_non_ref = r.se()?;
            let _offset_top_bottom = r.se()?;
            let n = r.ue()?;
            if n > 255 {
                return Err(format!("num_ref_frames_in_pic_order_cnt_cycle {n} > 255"));
            }
            for _ in 0..n {
                r.se()?;
            }
        }
        _ => {}
    }
    let _max_num_ref_frames = r.ue()?;
    let _gaps = r.flag()?;
    let _width_mbs = r.ue()?;
    let _height_map_units = r.ue()?;
    if !r.flag()? {
        let _mb_adaptive_frame_field = r.flag()?;
    }
    let _direct_8x8 = r.flag()?;
    if r.flag()? {
        for _ in 0..4 {
            r.ue()?;
        }
    }
    let mut info = ColourInfo {
        full_range: false,
        range_declared: false,
        matrix_coefficients: 2,
        chroma_format_idc,
        bit_depth_luma,
        bit_depth_chroma,
    };
    if r.flag()? {
        // vui_parameters()
        if r.flag()? {
            let aspect_ratio_idc = r.bits(8)?;
            if aspect_ratio_idc == 255 {
                r.bits(16)?;
                r.bits(16)?;
            }
        }
        if r.flag()? {
            let _overscan_appropriate = r.flag()?;
        }
        if r.flag()? {
            let _video_format = r.bits(3)?;
            info.range_declared = true;
            info.full_range = r.flag()?;
            if r.flag()? {
                let _colour_primaries = r.bits(8)?;
                let _transfer = r.bits(8)?;
                info.matrix_coefficients = r.bits(8)? as u8;
            }
        }
    }
    Ok(info)
}
