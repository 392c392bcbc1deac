//! Helpers shared by the integration tests.

use std::collections::HashMap;
use std::path::Path;

use tokenizers::Tokenizer;
use tokenizers::models::wordlevel::WordLevel;
use tokenizers::pre_tokenizers::whitespace::Whitespace;
use tokenizers::processors::template::TemplateProcessing;

/// Writes `dir/tokenizer.json`: a word-level tokenizer over `words` (ids in order), splitting
/// at whitespace, with `unknown` for other words and every text wrapped as `begin $A end`.
pub fn write_word_tokenizer(dir: &Path, words: &[&str], unknown: &str, begin: &str, end: &str) {
    let id = |word: &str| {
        words.iter().position(|w| *w == word).expect("the special token is in the vocabulary")
            as u32
    };
    let vocab: HashMap<String, u32> =
        words.iter().enumerate().map(|(i, w)| (w.to_string(), i as u32)).collect();
    let model = WordLevel::builder()
        .vocab(vocab.into_iter().collect())
        .unk_token(unknown.into())
        .build()
        .unwrap();
    let mut tokenizer = Tokenizer::new(model);
    tokenizer.with_pre_tokenizer(Some(Whitespace {}));
    let template = TemplateProcessing::builder()
        .try_single(format!("{begin} $A {end}"))
        .unwrap()
        .special_tokens(vec![(begin, id(begin)), (end, id(end))])
        .build()
        .unwrap();
    tokenizer.with_post_processor(Some(template));
    tokenizer.save(dir.join("tokenizer.json"), false).unwrap();
}
