//! What the TLS crypto of the client and the server (rustls with graviola: pure Rust, so
//! every target builds without a C compiler) needs of the CPU. Graviola asserts these
//! features at its first use; checking them first turns a panic inside a handshake into a
//! clear error when TLS is set up.

/// `None` when this CPU runs the TLS crypto, else which features it lacks.
pub fn tls_cpu_unsupported() -> Option<String> {
    let missing = missing_features();
    if missing.is_empty() {
        None
    } else {
        Some(format!(
            "this CPU lacks {} needed by the TLS crypto (graviola: x86_64 from about 2013 \
             with AES-NI, AVX2, BMI and ADX; aarch64 with AES, PMULL and SHA2)",
            missing.join(", ")
        ))
    }
}

#[cfg(target_arch = "x86_64")]
fn missing_features() -> Vec<&'static str> {
    let have = [
        ("aes", std::arch::is_x86_feature_detected!("aes")),
        (
            "pclmulqdq",
            std::arch::is_x86_feature_detected!("pclmulqdq"),
        ),
        ("ssse3", std::arch::is_x86_feature_detected!("ssse3")),
        ("avx", std::arch::is_x86_feature_detected!("avx")),
        ("avx2", std::arch::is_x86_feature_detected!("avx2")),
        ("bmi1", std::arch::is_x86_feature_detected!("bmi1")),
        ("bmi2", std::arch::is_x86_feature_detected!("bmi2")),
        ("adx", std::arch::is_x86_feature_detected!("adx")),
    ];
    have.iter().filter(|(_, ok)| !ok).map(|(n, _)| *n).collect()
}

#[cfg(target_arch = "aarch64")]
fn missing_features() -> Vec<&'static str> {
    let have = [
        ("neon", std::arch::is_aarch64_feature_detected!("neon")),
        ("aes", std::arch::is_aarch64_feature_detected!("aes")),
        ("pmull", std::arch::is_aarch64_feature_detected!("pmull")),
        ("sha2", std::arch::is_aarch64_feature_detected!("sha2")),
    ];
    have.iter().filter(|(_, ok)| !ok).map(|(n, _)| *n).collect()
}

#[cfg(not(any(target_arch = "x86_64", target_arch = "aarch64")))]
fn missing_features() -> Vec<&'static str> {
    vec!["an x86_64 or aarch64 processor"]
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_message_names_what_is_missing() {
        // On this machine (CI's kind) the crypto runs; the message format is checked on
        // whatever is missing, or on nothing.
        match tls_cpu_unsupported() {
            None => assert!(missing_features().is_empty()),
            Some(m) => {
                for f in missing_features() {
                    assert!(m.contains(f), "{m}");
                }
            }
        }
    }
}
