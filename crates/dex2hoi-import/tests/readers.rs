//! The numpy and pickle readers on files written by real numpy and pickle.

mod common;

use dex2hoi_import::array::{ArrayData, NdArray};
use dex2hoi_import::npy::{Npz, read_npy};
use dex2hoi_import::pickle::read_pickle;
use dex2hoi_import::{Field, Value};

fn numbers(value: &Value) -> (Vec<f64>, Vec<usize>) {
    Field::root("test", "", value).numbers_any_shape().unwrap()
}

#[test]
fn npz_arrays_of_every_plain_type_match_numpy() {
    let dir = common::fixtures().join("misc");
    let expected: serde_json::Value =
        serde_json::from_slice(&std::fs::read(dir.join("expected.json")).unwrap()).unwrap();
    let mut archive = Npz::open(&dir.join("arrays.npz")).unwrap();
    let mut names = archive.names();
    names.sort();
    assert_eq!(names.len(), expected.as_object().unwrap().len());
    for (name, want) in expected.as_object().unwrap() {
        let value = archive.read(name, "test array").unwrap();
        let shape: Vec<usize> = want["shape"]
            .as_array()
            .unwrap()
            .iter()
            .map(|d| d.as_u64().unwrap() as usize)
            .collect();
        let Value::Array(array) = &value else { panic!("{name}: {value:?}") };
        assert_eq!(array.shape, shape, "{name}");
        match &array.data {
            ArrayData::Str(texts) => {
                let want: Vec<&str> = want["values"]
                    .as_array()
                    .unwrap()
                    .iter()
                    .map(|v| v.as_str().unwrap())
                    .collect();
                assert_eq!(texts, &want, "{name}");
            }
            _ => {
                let want: Vec<f64> = want["values"]
                    .as_array()
                    .unwrap()
                    .iter()
                    .map(|v| v.as_f64().or_else(|| v.as_bool().map(f64::from)).unwrap())
                    .collect();
                assert_eq!(numbers(&value).0, want, "{name}");
            }
        }
    }
    let missing = archive.read("absent", "an array").unwrap_err().to_string();
    assert!(missing.contains("arrays.npz") && missing.contains("absent"), "{missing}");
}

/// The nested structure of `make_fixtures.py`, checked piece by piece.
fn check_nested(value: &Value, source: &str) {
    let root = Field::root(source, "", value);
    let params = root.get("params", "").unwrap();
    let (transl, shape) = params.get("transl", "").unwrap().numbers(&[Some(2), Some(3)]).unwrap();
    assert_eq!((transl, shape), ((0..6).map(f64::from).collect(), vec![2, 3]), "{source}");
    // Fortran order comes back in C order: arange(6).reshape(3, 2).
    let (pose, _) = params.get("pose", "").unwrap().numbers(&[Some(3), Some(2)]).unwrap();
    assert_eq!(pose, (0..6).map(f64::from).collect::<Vec<_>>(), "{source}");
    assert_eq!(root.get("name", "").unwrap().text().unwrap(), "mug");
    assert_eq!(root.get("count", "").unwrap().number().unwrap(), 3.0);
    assert_eq!(root.get("ratio", "").unwrap().number().unwrap(), 0.5);
    assert_eq!(root.get("big", "").unwrap().number().unwrap(), (1u64 << 40) as f64);
    assert_eq!(root.get("neg", "").unwrap().number().unwrap(), -7.0);
    assert_eq!(root.get("scalar", "").unwrap().number().unwrap(), -4.0);
    assert_eq!(*root.get("blob", "").unwrap().value(), Value::Bytes(vec![0, 1]), "{source}");
    assert_eq!(
        *root.get("flags", "").unwrap().value(),
        Value::List(vec![Value::Bool(true), Value::None])
    );
    assert_eq!(
        *root.get("pair", "").unwrap().value(),
        Value::Tuple(vec![Value::Int(1), Value::Str("a".into())])
    );
    // The same array referenced twice through the memo.
    let shared = root.get("shared", "").unwrap().items().unwrap();
    assert_eq!(shared.len(), 2);
    assert_eq!(shared[0].value(), shared[1].value());
    assert_eq!(shared[0].numbers_any_shape().unwrap().1, vec![2, 3]);
}

#[test]
fn pickles_of_every_protocol_and_object_arrays() {
    let dir = common::fixtures().join("misc");
    for protocol in 2..=5 {
        let path = dir.join(format!("nested_p{protocol}.pkl"));
        let bytes = std::fs::read(&path).unwrap();
        let (value, used) = read_pickle(&bytes, &path.display().to_string()).unwrap();
        assert_eq!(used, bytes.len());
        check_nested(&value, &format!("protocol {protocol}"));
    }
    // np.save of a dict: a 0-d object array whose item is the dict.
    let value = read_npy(&dir.join("object_dict.npy")).unwrap();
    assert!(matches!(&value, Value::Array(NdArray { shape, .. }) if shape.is_empty()));
    check_nested(&value, "object_dict.npy");
    let Value::Array(vector) = read_npy(&dir.join("object_vector.npy")).unwrap() else { panic!() };
    assert_eq!(
        vector.data,
        ArrayData::Object(vec![
            Value::Int(1),
            Value::Str("two".into()),
            Value::Float(3.0),
            Value::None
        ])
    );
}

#[test]
fn truncated_pickles_fail_with_the_file_name() {
    let path = common::fixtures().join("misc/nested_p4.pkl");
    let bytes = std::fs::read(&path).unwrap();
    for cut in [1, bytes.len() / 3, bytes.len() - 1] {
        let error = read_pickle(&bytes[..cut], "nested_p4.pkl").unwrap_err().to_string();
        assert!(error.contains("nested_p4.pkl"), "{error}");
    }
}
