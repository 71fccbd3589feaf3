//! Float arrays on the wire as packed little-endian bytes. CBOR writes each float as its own
//! item and ciborium tries each one as f16 and f32 first: at 192 x 384 that was about 40% of
//! the model server's CPU (docs/decisions/064). A byte string of `8 n` bytes
//! (`4 n` for an `f32` array: the published model's fields) is one copy each way, and the
//! values are the very bits they were (numpy reads it with `np.frombuffer(b, "<f8")` or
//! `"<f4"`). Human-readable formats (JSON: the live view, events) keep a plain list of numbers.
//! Either is read back, whatever the format says of itself (serde's buffering of a tagged enum
//! says it is human-readable when the CBOR under it is not).

use serde::de::{DeserializeOwned, Error, SeqAccess, Visitor};
use serde::{Deserializer, Serialize, Serializer};
use std::marker::PhantomData;

/// The most floats an array may hold (as many as the most cells of a list).
const MAX_FLOATS: usize = super::cells::MAX_CELLS;

/// A float as it travels: its width and its little-endian bytes.
pub trait Float: bytemuck::Pod + Serialize + DeserializeOwned {
    const NAME: &'static str;
    fn from_le(bytes: &[u8]) -> Self;
    fn le(self) -> Vec<u8>;
}

/// [`Float`] for a primitive float: its name, and its bytes through `from_le_bytes` /
/// `to_le_bytes`.
macro_rules! float {
    ($t:ty) => {
        impl Float for $t {
            const NAME: &'static str = stringify!($t);
            fn from_le(bytes: &[u8]) -> Self {
                <$t>::from_le_bytes(bytes.try_into().expect("a whole float's bytes"))
            }
            fn le(self) -> Vec<u8> {
                self.to_le_bytes().to_vec()
            }
        }
    };
}
float!(f64);
float!(f32);

/// What a packed array is in the protocol's schema ([`crate::protocol`]'s reference page): a
/// byte string of little-endian floats of type `T`, not a list of numbers.
pub struct PackedSchema<T>(PhantomData<T>);

impl<T: Float> schemars::JsonSchema for PackedSchema<T> {
    fn inline_schema() -> bool {
        true
    }
    fn schema_name() -> std::borrow::Cow<'static, str> {
        format!("Packed_{}", T::NAME).into()
    }
    fn json_schema(_: &mut schemars::SchemaGenerator) -> schemars::Schema {
        let width = std::mem::size_of::<T>();
        schemars::json_schema!({
            "type": "string",
            "contentEncoding": "binary",
            "x-wire": format!("bytes: packed little-endian {} (`np.frombuffer(b, \"<f{width}\")`)", T::NAME),
        })
    }
}

pub fn serialize<T: Float, S: Serializer>(values: &[T], s: S) -> Result<S::Ok, S::Error> {
    if s.is_human_readable() {
        return s.collect_seq(values);
    }
    s.serialize_bytes(&le_bytes(values))
}

/// The values' little-endian bytes: their memory as it is on a little-endian machine (no copy:
/// at 384 x 768 a model's 54 MB were copied once more for it), a copy elsewhere.
fn le_bytes<T: Float>(values: &[T]) -> std::borrow::Cow<'_, [u8]> {
    if cfg!(target_endian = "little") {
        std::borrow::Cow::Borrowed(bytemuck::cast_slice(values))
    } else {
        std::borrow::Cow::Owned(values.iter().flat_map(|v| v.le()).collect())
    }
}

pub fn deserialize<'de, T: Float, D: Deserializer<'de>>(d: D) -> Result<Vec<T>, D::Error> {
    d.deserialize_any(Packed(PhantomData))
}

struct Packed<T>(PhantomData<T>);

impl<'de, T: Float> Visitor<'de> for Packed<T> {
    type Value = Vec<T>;

    fn expecting(&self, f: &mut std::fmt::Formatter) -> std::fmt::Result {
        write!(f, "floats: packed little-endian {} bytes, or a list", T::NAME)
    }

    fn visit_bytes<E: Error>(self, b: &[u8]) -> Result<Vec<T>, E> {
        let width = std::mem::size_of::<T>();
        if !b.len().is_multiple_of(width) || b.len() / width > MAX_FLOATS {
            return Err(E::custom(format!(
                "packed floats: {} bytes is not a whole number of {}s, or more than {MAX_FLOATS} of them",
                b.len(),
                T::NAME
            )));
        }
        Ok(b.chunks_exact(width).map(T::from_le).collect())
    }

    fn visit_byte_buf<E: Error>(self, b: Vec<u8>) -> Result<Vec<T>, E> {
        self.visit_bytes(&b)
    }

    fn visit_seq<A: SeqAccess<'de>>(self, mut seq: A) -> Result<Vec<T>, A::Error> {
        let mut out = Vec::with_capacity(seq.size_hint().unwrap_or(0).min(MAX_FLOATS));
        while let Some(v) = seq.next_element::<T>()? {
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

    #[derive(Debug, PartialEq, serde::Serialize, serde::Deserialize)]
    struct Floats32(#[serde(with = "super")] Vec<f32>);

    /// An `f32` array (the published model's) is 4 bytes a value, every bit back; a byte string
    /// that is not whole f32s is refused, saying which width it wanted.
    #[test]
    fn f32_arrays_travel_as_four_bytes_a_value() {
        let v = vec![0.1f32, -0.0, f32::MIN_POSITIVE / 3.0, f32::INFINITY, 3.0e38];
        let mut bytes = vec![];
        ciborium::into_writer(&Floats32(v.clone()), &mut bytes).unwrap();
        assert_eq!(
            bytes.len(),
            1 + 4 * v.len(),
            "a byte string of 20 bytes after its header"
        );
        let back: Floats32 = ciborium::from_reader(&bytes[..]).unwrap();
        let bits = |v: &[f32]| v.iter().map(|x| x.to_bits()).collect::<Vec<_>>();
        assert_eq!(bits(&back.0), bits(&v));
        assert_eq!(serde_json::to_string(&Floats32(vec![0.5, 2.0])).unwrap(), "[0.5,2.0]");
        let mut odd = vec![];
        ciborium::into_writer(&serde_bytes_like(&[0u8; 6]), &mut odd).unwrap();
        let err = ciborium::from_reader::<Floats32, _>(&odd[..]).unwrap_err().to_string();
        assert!(err.contains("whole number of f32s"), "{err}");
    }

    fn serde_bytes_like(b: &[u8]) -> ciborium::Value {
        ciborium::Value::Bytes(b.to_vec())
    }
}
