//! Value parsers of the command line's flags (clap `value_parser`s), shared by the
//! subcommand modules.

use harmonic_core::map::Dims;
use harmonic_sim::link::fault::DEFAULT_BURST_LEN;
use harmonic_sim::sensors::camera::StereoNoise;
use harmonic_sim::sensors::faults::DriftConfig;

/// `--prefilter`: `none`, `dog` (the default Difference of Gaussians) or `dog:SIGMA_SMALL:SIGMA_LARGE`.
pub fn parse_prefilter(s: &str) -> Result<harmonic_core::stereo::Prefilter, String> {
    use harmonic_core::stereo::Prefilter;
    match s {
        "none" => return Ok(Prefilter::None),
        "dog" => return Ok(Prefilter::DEFAULT_DOG),
        _ => {}
    }
    let bad = || format!("expected `dog`, `dog:SIGMA_SMALL:SIGMA_LARGE` or `none`, got `{s}`");
    let mut parts = s.split(':');
    if parts.next() != Some("dog") {
        return Err(bad());
    }
    let mut sigma = || parts.next().and_then(|v| v.parse::<f32>().ok()).ok_or_else(bad);
    let (sigma_small, sigma_large) = (sigma()?, sigma()?);
    Ok(Prefilter::DoG {
        sigma_small,
        sigma_large,
    })
}

/// A voxel as `X,Y,Z` indices (`solve --source`).
pub fn parse_voxel(s: &str) -> Result<[usize; 3], String> {
    let n: Vec<usize> = s.split(',').filter_map(|p| p.trim().parse().ok()).collect();
    match (n.as_slice(), s.split(',').count()) {
        ([x, y, z], 3) => Ok([*x, *y, *z]),
        _ => Err(format!("expected three voxel indices X,Y,Z, got `{s}`")),
    }
}

/// A grid size `NXxNYxNZ` with NX, NY >= 16 and NZ >= 8 (`bench-solve --sizes`).
pub fn parse_dims(s: &str) -> Result<Dims, String> {
    let parts: Vec<&str> = s.split('x').collect();
    let n: Vec<usize> = parts.iter().filter_map(|p| p.parse().ok()).collect();
    match n.as_slice() {
        [x, y, z] if parts.len() == 3 && *x >= 16 && *y >= 16 && *z >= 8 => {
            Dims::new(*x, *y, *z).map_err(|e| format!("`{s}`: {e:?}"))
        }
        _ => Err(format!(
            "expected NXxNYxNZ with NX, NY >= 16 and NZ >= 8, got `{s}`"
        )),
    }
}

/// Exactly `N` comma-separated finite numbers >= 0, or `None`.
fn non_negative<const N: usize>(s: &str) -> Option<[f32; N]> {
    let mut out = [0.0; N];
    let mut parts = s.split(',');
    for o in &mut out {
        let v: f32 = parts.next()?.trim().parse().ok()?;
        if !(v.is_finite() && v >= 0.0) {
            return None;
        }
        *o = v;
    }
    parts.next().is_none().then_some(out)
}

/// `--drift`: `SIGMA_POS_M,SIGMA_YAW_RAD`, two numbers >= 0.
pub fn parse_drift(s: &str) -> Result<DriftConfig, String> {
    let [p, y] = non_negative(s)
        .ok_or_else(|| format!("expected SIGMA_POS_M,SIGMA_YAW_RAD (two numbers >= 0), got `{s}`"))?;
    Ok(DriftConfig {
        sigma_position_m: p,
        sigma_yaw_rad: y,
    })
}

/// `--grid-offset`: `X,Y,Z` in metres, each at least 0 (the scenario's voxel size bounds them
/// from above; the run checks that).
pub fn parse_grid_offset(s: &str) -> Result<[f32; 3], String> {
    non_negative(s).ok_or_else(|| format!("expected X,Y,Z (three numbers >= 0, metres), got `{s}`"))
}

/// A baud rate: a positive integer.
pub fn parse_baud(s: &str) -> Result<u32, String> {
    match s.parse::<u32>() {
        Ok(v) if v > 0 => Ok(v),
        _ => Err(format!("expected a baud rate (a positive integer), got `{s}`")),
    }
}

/// A probability: a finite number from 0 to 1.
pub fn parse_probability(s: &str) -> Result<f64, String> {
    match s.parse::<f64>() {
        Ok(v) if v.is_finite() && (0.0..=1.0).contains(&v) => Ok(v),
        _ => Err(format!("expected a probability between 0 and 1, got `{s}`")),
    }
}

/// `--link-burst`: `RATE[:BYTES]`, a probability and a positive burst length (default
/// [`DEFAULT_BURST_LEN`]).
pub fn parse_burst(s: &str) -> Result<(f64, u32), String> {
    let (rate, len) = match s.split_once(':') {
        Some((r, l)) => (r, Some(l)),
        None => (s, None),
    };
    let rate = parse_probability(rate).map_err(|e| format!("`{s}`: {e} (RATE[:BYTES])"))?;
    let len = match len {
        None => DEFAULT_BURST_LEN,
        Some(l) => match l.parse::<u32>() {
            Ok(n) if n > 0 => n,
            _ => {
                return Err(format!(
                    "`{s}`: burst length `{l}` is not a positive number of bytes"
                ))
            }
        },
    };
    Ok((rate, len))
}

/// A finite number > 0.
pub fn parse_positive(s: &str) -> Result<f32, String> {
    match s.parse::<f32>() {
        Ok(v) if v.is_finite() && v > 0.0 => Ok(v),
        _ => Err(format!("expected a positive number, got `{s}`")),
    }
}

/// A finite number ≥ 0 (0 usually turns a rule off).
pub fn parse_non_negative(s: &str) -> Result<f32, String> {
    match s.parse::<f32>() {
        Ok(v) if v.is_finite() && v >= 0.0 => Ok(v),
        _ => Err(format!("expected a number ≥ 0, got `{s}`")),
    }
}

/// A vehicle radius: 0 to 0.6 m.
pub fn parse_radius(s: &str) -> Result<f32, String> {
    match s.parse::<f32>() {
        Ok(v) if v.is_finite() && (0.0..=0.6).contains(&v) => Ok(v),
        _ => Err(format!("expected a radius between 0 and 0.6 m, got `{s}`")),
    }
}

/// `--noise`: `stereo`, `stereo:SIGMA_PX` or `stereo:SIGMA_PX:FILTER_PX` (odd, 1-15).
pub fn parse_noise(s: &str) -> Result<StereoNoise, String> {
    let mut parts = s.split(':');
    let kind = parts.next().unwrap_or("");
    if kind != "stereo" {
        return Err(format!(
            "unknown noise model `{kind}` (expected `stereo`, `stereo:SIGMA_PX` or `stereo:SIGMA_PX:FILTER_PX`)"
        ));
    }
    let mut noise = StereoNoise::default();
    if let Some(v) = parts.next() {
        noise.sigma_px = match v.parse::<f32>() {
            Ok(x) if x.is_finite() && x >= 0.0 => x,
            _ => {
                return Err(format!(
                    "bad disparity sigma `{v}` (expected a number of pixels ≥ 0)"
                ))
            }
        };
    }
    if let Some(w) = parts.next() {
        noise.filter_px = match w.parse::<u8>() {
            Ok(x) if x % 2 == 1 && x <= 15 => x,
            _ => {
                return Err(format!(
                    "bad median window `{w}` (expected an odd number of pixels from 1 to 15; 1 = no filter)"
                ))
            }
        };
    }
    if parts.next().is_some() {
        return Err(format!("`{s}`: too many fields (stereo[:SIGMA_PX[:FILTER_PX]])"));
    }
    Ok(noise)
}

/// Operator commands at simulated times, for `explore --operator`.
#[derive(Debug, Clone, PartialEq)]
pub struct OperatorScript(pub Vec<(f64, harmonic_core::operator::OperatorCommand)>);

/// `COMMAND@SECONDS,...` (start, pause, resume, abort, home), in time order.
pub fn parse_operator_script(s: &str) -> Result<OperatorScript, String> {
    use harmonic_core::operator::OperatorCommand as C;
    let mut script = Vec::new();
    for item in s.split(',').map(str::trim).filter(|i| !i.is_empty()) {
        let (name, at) = item
            .split_once('@')
            .ok_or_else(|| format!("`{item}`: expected COMMAND@SECONDS, e.g. pause@30"))?;
        let command = match name.trim() {
            "start" => C::Start,
            "pause" => C::Pause,
            "resume" => C::Resume,
            "abort" => C::Abort,
            "home" => C::ReturnHome,
            other => {
                return Err(format!(
                    "`{other}`: not a command (start, pause, resume, abort, home)"
                ))
            }
        };
        let t: f64 = at
            .trim()
            .parse()
            .map_err(|_| format!("`{at}`: not a time in seconds"))?;
        if !(t.is_finite() && t >= 0.0) {
            return Err(format!("`{at}`: the time must be 0 s or later"));
        }
        script.push((t, command));
    }
    if script.is_empty() {
        return Err("no command given".into());
    }
    script.sort_by(|a, b| a.0.total_cmp(&b.0));
    Ok(OperatorScript(script))
}

#[cfg(test)]
mod tests {
    use super::*;
    use harmonic_core::operator::OperatorCommand as C;

    #[test]
    fn lists_of_non_negative_numbers_have_their_exact_length() {
        assert_eq!(parse_grid_offset(" 0.05, 0,0.025").unwrap(), [0.05, 0.0, 0.025]);
        let d = parse_drift("0.1,0.015").unwrap();
        assert_eq!((d.sigma_position_m, d.sigma_yaw_rad), (0.1, 0.015));
        for bad in ["0.05,0", "0,0,0,0", "0,-0.01,0", "0,nan,0", "0,,0", ""] {
            assert!(parse_grid_offset(bad).unwrap_err().contains("X,Y,Z"), "{bad}");
        }
        for bad in ["0.1", "0.1,0.2,0.3", "-1,0", "inf,0"] {
            assert!(parse_drift(bad).is_err(), "{bad}");
        }
    }

    #[test]
    fn a_rule_off_switch_takes_zero_and_refuses_what_is_not_a_number_at_or_above_it() {
        assert_eq!(parse_non_negative("0").unwrap(), 0.0);
        assert_eq!(parse_non_negative("0.5").unwrap(), 0.5);
        for bad in ["-0.1", "nan", "inf", "", "half"] {
            assert!(parse_non_negative(bad).unwrap_err().contains("≥ 0"), "{bad}");
        }
    }

    #[test]
    fn operator_scripts_parse_in_time_order_and_bad_ones_say_why() {
        let s = parse_operator_script("resume@45, pause@30,start@0.5,abort@70").unwrap();
        assert_eq!(
            s.0,
            [
                (0.5, C::Start),
                (30.0, C::Pause),
                (45.0, C::Resume),
                (70.0, C::Abort)
            ]
        );
        for (bad, why) in [
            ("pause", "COMMAND@SECONDS"),
            ("jump@3", "not a command"),
            ("pause@x", "not a time"),
            ("pause@-1", "0 s or later"),
            ("pause@inf", "0 s or later"),
            ("", "no command"),
        ] {
            let err = parse_operator_script(bad).unwrap_err();
            assert!(err.contains(why), "{bad}: {err}");
        }
    }
}
