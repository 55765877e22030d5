//! The calibration file: versioned, human-readable JSON (docs/formats.md).
//! Loading checks the version and every field, and a malformed file is an
//! [`Error::Calibration`] naming the file and the position, never a panic.

use std::path::{Path, PathBuf};

use serde::{Deserialize, Serialize};

use super::*;

/// How a calibration file records the segmentation thresholds it was fitted
/// with: a label (`low`, `mid`, `high` for a preset, otherwise `custom`) and the
/// numbers, full-resolution pixels. The kernel shape is written only when it is
/// not the presets' rectangle.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
struct ThresholdsFile {
    preset: String,
    magnitude: f32,
    sum: f32,
    erode: u32,
    dilate: u32,
    #[serde(default, skip_serializing_if = "is_rect")]
    shape: Shape,
}

fn is_rect(shape: &Shape) -> bool {
    *shape == Shape::Rect
}

impl ThresholdsFile {
    fn new(t: &Thresholds) -> Self {
        ThresholdsFile {
            preset: t
                .as_preset()
                .map_or("custom", ThresholdPreset::name)
                .to_string(),
            magnitude: t.magnitude,
            sum: t.sum,
            erode: u32::try_from(t.erode).unwrap_or(u32::MAX),
            dilate: u32::try_from(t.dilate).unwrap_or(u32::MAX),
            shape: t.shape,
        }
    }

    fn thresholds(&self) -> Thresholds {
        Thresholds {
            magnitude: self.magnitude,
            sum: self.sum,
            erode: self.erode as usize,
            dilate: self.dilate as usize,
            shape: self.shape,
        }
    }
}

/// Serde for [`SensorSetup::thresholds`] in the calibration file's form.
pub(super) mod thresholds_format {
    use serde::{Deserialize, Deserializer, Serialize, Serializer};

    use super::{Thresholds, ThresholdsFile};

    pub fn serialize<S: Serializer>(t: &Thresholds, s: S) -> Result<S::Ok, S::Error> {
        ThresholdsFile::new(t).serialize(s)
    }

    pub fn deserialize<'de, D: Deserializer<'de>>(d: D) -> Result<Thresholds, D::Error> {
        Ok(ThresholdsFile::deserialize(d)?.thresholds())
    }
}

impl Calibration {
    /// The calibration as pretty, human-readable JSON (`"version": 1`).
    /// Arrays of plain values (exponent rows, coefficients) stay on one line.
    pub fn to_json_string(&self) -> String {
        let pretty = serde_json::to_string_pretty(&self.file_repr())
            .expect("serializing plain data with string keys cannot fail");
        let mut s = collapse_scalar_arrays(&pretty);
        s.push('\n');
        s
    }

    /// What the file holds, by reference.
    fn file_repr(&self) -> CalibrationRef<'_> {
        CalibrationRef {
            version: FORMAT_VERSION,
            geometry: &self.setup.geometry,
            crop: &self.setup.crop,
            thresholds: ThresholdsFile::new(&self.setup.thresholds),
            pipeline: self.setup.pipeline.as_ref(),
            g1: &self.g1,
            g2: &self.g2,
            gx: &self.gx,
            gy: &self.gy,
            gz: &self.gz,
            report: self.report.as_ref(),
            profile: self.profile.as_ref(),
            guard: self.guard.as_ref(),
            min_normal_n: self.min_normal_n,
            column_correction: self.column_correction.as_ref(),
            force_uncertainty: self.uncertainty.as_ref(),
        }
    }

    /// Writes the calibration to `path` as JSON. A calibration holding a NaN
    /// or infinite number (a report's error of an empty split, say) is
    /// refused ([`Error::Format`] naming the field) and nothing is written.
    pub fn save(&self, path: impl AsRef<Path>) -> Result<()> {
        let path = path.as_ref();
        crate::io::check_finite(&self.file_repr(), path)?;
        std::fs::write(path, self.to_json_string()).map_err(|e| Error::io(path, e))
    }

    /// Reads a calibration file. Errors: the file cannot be read, or is a
    /// directory, a FIFO or a device ([`Error::Io`]); it is larger than
    /// [`crate::io::MAX_CALIBRATION_BYTES`] ([`Error::Format`]); it is not
    /// JSON, has another version, misses a polynomial, holds an inconsistent
    /// one, or a size beyond its bound (docs/formats.md)
    /// ([`Error::Calibration`] naming the file, with line and column where
    /// JSON parsing failed).
    pub fn load(path: impl AsRef<Path>) -> Result<Self> {
        let path = path.as_ref();
        let bytes = crate::io::read_capped(path, crate::io::MAX_CALIBRATION_BYTES)?;
        let text = String::from_utf8(bytes).map_err(|e| Error::Calibration {
            path: Some(path.to_path_buf()),
            message: format!("not UTF-8 text: {e}"),
        })?;
        Self::parse(&text, Some(path.to_path_buf()))
    }

    /// Reads a calibration from JSON text (errors as for [`Calibration::load`],
    /// without a file name).
    pub fn from_json_str(text: &str) -> Result<Self> {
        Self::parse(text, None)
    }

    fn parse(text: &str, path: Option<PathBuf>) -> Result<Self> {
        let err = |message: String| Error::Calibration {
            path: path.clone(),
            message,
        };
        // First as an untyped value: syntax errors with their position, and the
        // version checked before the layout that depends on it.
        let value: serde_json::Value = serde_json::from_str(text).map_err(|e| {
            err(format!(
                "malformed JSON at line {}, column {}: {}",
                e.line(),
                e.column(),
                strip_position(&e)
            ))
        })?;
        let obj = value
            .as_object()
            .ok_or_else(|| err("the top level must be a JSON object".into()))?;
        match obj.get("version") {
            None => {
                return Err(err(format!(
                    "no `version` field (this library reads version {FORMAT_VERSION})"
                )));
            }
            Some(v) => match v.as_u64() {
                Some(n) if n == u64::from(FORMAT_VERSION) => {}
                _ => {
                    return Err(err(format!(
                        "version {v} is not supported (this library reads version {FORMAT_VERSION})"
                    )));
                }
            },
        }
        for name in [
            "geometry",
            "crop",
            "thresholds",
            "g1",
            "g2",
            "gx",
            "gy",
            "gz",
        ] {
            if !obj.contains_key(name) {
                let what = if name.starts_with('g') && name.len() == 2 {
                    "polynomial"
                } else {
                    "field"
                };
                return Err(err(format!("missing {what} `{name}`")));
            }
        }
        // Then typed, from the text again, so that errors carry positions.
        let repr: CalibrationOwned = serde_json::from_str(text).map_err(|e| {
            err(format!(
                "line {}, column {}: {}",
                e.line(),
                e.column(),
                strip_position(&e)
            ))
        })?;
        let c = Calibration {
            setup: SensorSetup {
                geometry: repr.geometry,
                crop: repr.crop,
                thresholds: repr.thresholds.thresholds(),
                pipeline: repr.pipeline,
            },
            g1: repr.g1,
            g2: repr.g2,
            gx: repr.gx,
            gy: repr.gy,
            gz: repr.gz,
            report: repr.report,
            profile: repr.profile,
            guard: repr.guard,
            min_normal_n: repr.min_normal_n,
            column_correction: repr.column_correction,
            uncertainty: repr.force_uncertainty,
        };
        c.check().map_err(err)?;
        Ok(c)
    }
}

/// serde_json's message without its trailing " at line L column C" (we put the
/// position first, in words).
fn strip_position(e: &serde_json::Error) -> String {
    let s = e.to_string();
    match s.rfind(" at line ") {
        Some(i) => s[..i].to_string(),
        None => s,
    }
}

#[derive(Serialize)]
struct CalibrationRef<'a> {
    version: u32,
    geometry: &'a SensorGeometry,
    crop: &'a Roi,
    thresholds: ThresholdsFile,
    #[serde(skip_serializing_if = "Option::is_none")]
    pipeline: Option<&'a PipelineSettings>,
    g1: &'a Polynomial,
    g2: &'a Polynomial,
    gx: &'a Polynomial,
    gy: &'a Polynomial,
    gz: &'a Polynomial,
    #[serde(skip_serializing_if = "Option::is_none")]
    report: Option<&'a CalibrationReport>,
    #[serde(skip_serializing_if = "Option::is_none")]
    profile: Option<&'a ProfileModel>,
    #[serde(skip_serializing_if = "Option::is_none")]
    guard: Option<&'a ForceGuard>,
    #[serde(skip_serializing_if = "Option::is_none")]
    min_normal_n: Option<f64>,
    #[serde(skip_serializing_if = "Option::is_none")]
    column_correction: Option<&'a ColumnCorrection>,
    #[serde(skip_serializing_if = "Option::is_none")]
    force_uncertainty: Option<&'a ForceUncertainty>,
}

#[derive(Deserialize)]
struct CalibrationOwned {
    #[allow(dead_code)]
    version: u32,
    geometry: SensorGeometry,
    crop: Roi,
    thresholds: ThresholdsFile,
    #[serde(default)]
    pipeline: Option<PipelineSettings>,
    g1: Polynomial,
    g2: Polynomial,
    gx: Polynomial,
    gy: Polynomial,
    gz: Polynomial,
    #[serde(default)]
    report: Option<CalibrationReport>,
    #[serde(default)]
    profile: Option<ProfileModel>,
    #[serde(default)]
    guard: Option<ForceGuard>,
    #[serde(default)]
    min_normal_n: Option<f64>,
    #[serde(default)]
    column_correction: Option<ColumnCorrection>,
    #[serde(default)]
    force_uncertainty: Option<ForceUncertainty>,
}

/// Rewrites pretty JSON so that arrays holding only scalars sit on one line
/// (`[1, 0, 2]`): exponent rows and coefficient lists stay readable instead of
/// one number per line. Strings are copied untouched.
fn collapse_scalar_arrays(s: &str) -> String {
    let b = s.as_bytes();
    let mut out = String::with_capacity(s.len());
    let mut i = 0;
    let mut in_str = false;
    let mut esc = false;
    // Copies the char starting at byte i and returns the next index.
    let next_char = |i: usize| i + s[i..].chars().next().map_or(1, char::len_utf8);
    while i < b.len() {
        let c = b[i];
        if in_str {
            if esc {
                esc = false;
            } else if c == b'\\' {
                esc = true;
            } else if c == b'"' {
                in_str = false;
            }
            let j = next_char(i);
            out.push_str(&s[i..j]);
            i = j;
            continue;
        }
        if c == b'"' {
            in_str = true;
            out.push('"');
            i += 1;
            continue;
        }
        if c == b'[' {
            // Find the matching ']' if no nested container comes first.
            let (mut j, mut st, mut es) = (i + 1, false, false);
            let mut end = None;
            while j < b.len() {
                let d = b[j];
                if st {
                    if es {
                        es = false;
                    } else if d == b'\\' {
                        es = true;
                    } else if d == b'"' {
                        st = false;
                    }
                } else if d == b'"' {
                    st = true;
                } else if d == b'[' || d == b'{' {
                    break;
                } else if d == b']' {
                    end = Some(j);
                    break;
                }
                j += 1;
            }
            if let Some(end) = end {
                let (mut st, mut es) = (false, false);
                let mut k = i;
                while k <= end {
                    let d = b[k];
                    let nk = next_char(k);
                    if st {
                        if es {
                            es = false;
                        } else if d == b'\\' {
                            es = true;
                        } else if d == b'"' {
                            st = false;
                        }
                        out.push_str(&s[k..nk]);
                    } else if d == b'"' {
                        st = true;
                        out.push('"');
                    } else if d == b',' {
                        out.push_str(", ");
                    } else if !d.is_ascii_whitespace() {
                        out.push_str(&s[k..nk]);
                    }
                    k = nk;
                }
                i = end + 1;
                continue;
            }
        }
        let j = next_char(i);
        out.push_str(&s[i..j]);
        i = j;
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    fn json_value() -> impl Strategy<Value = serde_json::Value> {
        use serde_json::Value;
        let leaf = prop_oneof![
            Just(Value::Null),
            any::<bool>().prop_map(Value::Bool),
            any::<i32>().prop_map(Value::from),
            "[ \\[\\]{},:\"\\\\a-zé]{0,8}".prop_map(Value::String),
        ];
        leaf.prop_recursive(4, 40, 6, |inner| {
            prop_oneof![
                prop::collection::vec(inner.clone(), 0..6).prop_map(Value::Array),
                prop::collection::btree_map("[a-z\\[ ]{1,4}", inner, 0..5)
                    .prop_map(|m| Value::Object(m.into_iter().collect())),
            ]
        })
    }

    proptest! {
        #![proptest_config(proptest::test_runner::Config {
            cases: 128,
            rng_algorithm: proptest::test_runner::RngAlgorithm::ChaCha,
            rng_seed: proptest::test_runner::RngSeed::Fixed(6),
            failure_persistence: None,
            ..proptest::test_runner::Config::default()
        })]

        /// Collapsing arrays only changes whitespace outside strings: the
        /// document still parses to the same value.
        #[test]
        fn collapse_preserves_any_document(v in json_value()) {
            let pretty = serde_json::to_string_pretty(&v).unwrap();
            let c = collapse_scalar_arrays(&pretty);
            let back: serde_json::Value = serde_json::from_str(&c).unwrap();
            prop_assert_eq!(back, v);
        }
    }

    #[test]
    fn collapse_keeps_nested_and_strings() {
        let v = serde_json::json!({"a": [[1, 2], [3]], "b": ["x [ , ]", "y"], "c": {"d": []}});
        let pretty = serde_json::to_string_pretty(&v).unwrap();
        let c = collapse_scalar_arrays(&pretty);
        assert!(c.contains("[1, 2]"), "{c}");
        assert!(c.contains("[\"x [ , ]\", \"y\"]"), "{c}");
        let back: serde_json::Value = serde_json::from_str(&c).unwrap();
        assert_eq!(back, v);
    }
}
