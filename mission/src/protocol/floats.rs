//! Float arrays on the wire as packed little-endian bytes. CBOR writes each float as its own
//! item and ciborium tries each one as f16 and f32 first: at 192 x 384 that was about 40% of
//! the model server's CPU (README, "Where an epoch's time goes"). A byte string of `8 n` bytes
//! is one copy each way, and the values are the very bits they were (numpy reads it with
//! `np.frombuffer(b, "<f8")`). Human-readable formats (JSON: the live view, events) keep a
//! plain list of numbers. Either is read back, whatever the format says of itself (serde's
//! buffering of a tagged enum says it is human-readable when the CBOR under it is not).

use serde::de::{Error, SeqAccess, Visitor};
use serde::{Deserializer, Serializer};

/// The most floats an array may hold (as many as the most cells of a list).
const MAX_FLOATS: usize = super::cells::MAX_CELLS;

pub fn serialize<S: Serializer>(values: &[f64], s: S) -> Result<S::Ok, S::Error> {
    if s.is_human_readable() {
        return s.collect_seq(values);
    }
    s.serialize_bytes(&le_bytes(values))
}

/// The values' little-endian bytes: their memory as it is on a little-endian machine (no copy:
/// at 384 x 768 a model's 54 MB were copied once more for it), a copy elsewhere.
fn le_bytes(values: &[f64]) -> std::borrow::Cow<'_, [u8]> {
    if cfg!(target_endian = "little") {
        std::borrow::Cow::Borrowed(bytemuck::cast_slice(values))
    } else {
        std::borrow::Cow::Owned(values.iter().flat_map(|v| v.to_le_bytes()).collect())
    }
}

pub fn deserialize<'de, D: Deserializer<'de>>(d: D) -> Result<Vec<f64>, D::Error> {
    d.deserialize_any(Packed)
}

struct Packed;

impl<'de> Visitor<'de> for Packed {
    type Value = Vec<f64>;

    fn expecting(&self, f: &mut std::fmt::Formatter) -> std::fmt::Result {
        f.write_str("floats: packed little-endian f64 bytes, or a list")
    }

    fn visit_bytes<E: Error>(self, b: &[u8]) -> Result<Vec<f64>, E> {
        if !b.len().is_multiple_of(8) || b.len() / 8 > MAX_FLOATS {
            return Err(E::custom(format!(
                "packed floats: {} bytes is not a whole number of f64s, or more than {MAX_FLOATS} of them",
                b.len()
            )));
        }
        Ok(b.chunks_exact(8)
            .map(|c| f64::from_le_bytes(c.try_into().expect("8 bytes")))
            .collect())
    }

    fn visit_byte_buf<E: Error>(self, b: Vec<u8>) -> Result<Vec<f64>, E> {
        self.visit_bytes(&b)
    }

    fn visit_seq<A: SeqAccess<'de>>(self, mut seq: A) -> Result<Vec<f64>, A::Error> {
        let mut out = Vec::with_capacity(seq.size_hint().unwrap_or(0).min(MAX_FLOATS));
        while let Some(v) = seq.next_element::<f64>()? {
            if out.len() == MAX_FLOATS {
                return Err(A::Error::custom(format!("more than {MAX_FLOATS} floats")));
            }
            out.push(v);
        }
        Ok(out)
    }
}

#[cfg(test)]
mod tests {
    #[derive(Debug, PartialEq, serde::Serialize, serde::Deserialize)]
    struct Floats(#[serde(with = "super")] Vec<f64>);

    /// Every bit comes back (signed zeros, subnormals, infinities and NaN's payload too), in
    /// CBOR as 8 bytes a value plus a short header, in JSON as a list; a byte string that is not
    /// whole f64s is refused.
    #[test]
    fn floats_round_trip_bit_for_bit_packed_in_cbor_and_as_a_list_in_json() {
        let v = vec![
            0.1,
            -0.0,
            f64::MIN_POSITIVE / 3.0,
            f64::INFINITY,
            f64::from_bits(0x7ff8_0000_dead_beef),
            1e300,
        ];
        let mut bytes = vec![];
        ciborium::into_writer(&Floats(v.clone()), &mut bytes).unwrap();
        assert_eq!(
            bytes.len(),
            2 + 8 * v.len(),
            "a byte string of 48 bytes after its header"
        );
        let back: Floats = ciborium::from_reader(&bytes[..]).unwrap();
        let bits = |v: &[f64]| v.iter().map(|x| x.to_bits()).collect::<Vec<_>>();
        assert_eq!(bits(&back.0), bits(&v));
        assert_eq!(serde_json::to_string(&Floats(vec![0.5, 2.0])).unwrap(), "[0.5,2.0]");
        assert_eq!(
            serde_json::from_str::<Floats>("[0.5,2.0]").unwrap(),
            Floats(vec![0.5, 2.0])
        );
        let mut odd = vec![];
        ciborium::into_writer(&serde_bytes_like(&[0u8; 12]), &mut odd).unwrap();
        assert!(ciborium::from_reader::<Floats, _>(&odd[..]).is_err());
    }

    fn serde_bytes_like(b: &[u8]) -> ciborium::Value {
        ciborium::Value::Bytes(b.to_vec())
    }
}
