//! Descriptions a person would write: a phrase grammar with synonyms and phrasings for every
//! task family, in the third person ("The person grabs the cup with the right hand ...") and as
//! commands ("Pick up the mug with your left hand and ...").
//!
//! The grammar is data: per task a table of sentence templates with slots, and shared tables of
//! synonyms the slots draw from. A small engine fills the slots. About a fifth of the templates
//! of each task are held out of training ([`Phrasing::HeldOut`]), so an evaluation can ask for
//! phrasings the model never saw, written only with words it knows.
//!
//! Template syntax:
//! - `{name}`: a variable of the description (`obj`, `h`, ...) or a random alternative of the
//!   table `name`, filled recursively;
//! - `{name:var}`: the same, with `{side}` inside it meaning the side word held by `var` (`h`:
//!   the acting hand, `o`: the other hand, `d`: where an object goes, `l`/`r`: left/right);
//! - `{third|command}` (inline, or a whole table alternative `third|command`): the verb form
//!   of a statement ("picks up") or of a command ("pick up").

use std::collections::BTreeSet;

use rand::Rng;
use rand_chacha::ChaCha8Rng;

use dex2hoi_data::character::Hand;

/// Which phrasings a description is drawn from: the training grammar, or the phrasings held
/// out of training for evaluation.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Phrasing {
    /// The templates a model is trained on.
    Training,
    /// The templates kept from training; they use only words the training grammar produces.
    HeldOut,
}

/// What a description says: the task and its objects (catalogue names), hands and directions.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Description<'a> {
    /// One hand moves an object to one side (`towards`: the side it is put down on, from the
    /// person's point of view; `Hand::Left` means to their left).
    PickPlace {
        /// The catalogue name of the object.
        object: &'a str,
        /// The hand that moves it.
        hand: Hand,
        /// The side it is put down on.
        towards: Hand,
    },
    /// One hand lifts an object, turns it to look at it and puts it back.
    Inspect {
        /// The catalogue name of the object.
        object: &'a str,
        /// The hand that holds it.
        hand: Hand,
    },
    /// Both hands lift a wide object and put it back.
    LiftBoth {
        /// The catalogue name of the object.
        object: &'a str,
    },
    /// Picked up with `from`, passed to the other hand, put down on the other hand's side.
    Handover {
        /// The catalogue name of the object.
        object: &'a str,
        /// The hand that picks it up and gives it away.
        from: Hand,
    },
    /// One object in each hand, held up together and put back.
    HoldTwo {
        /// The object the left hand holds.
        left: &'a str,
        /// The object the right hand holds.
        right: &'a str,
    },
    /// Two objects trade places; `left` stands on the person's left at the start.
    Swap {
        /// The object on the left at the start.
        left: &'a str,
        /// The object on the right at the start.
        right: &'a str,
    },
    /// `hand` pours from `pourer` into `receiver`, which the other hand steadies.
    Pour {
        /// The object poured from.
        pourer: &'a str,
        /// The object poured into.
        receiver: &'a str,
        /// The pouring hand.
        hand: Hand,
    },
    /// `hand` puts `moved` down next to `anchor`, on the hand's side of it.
    MoveNextTo {
        /// The object that is moved.
        moved: &'a str,
        /// The object it ends up next to.
        anchor: &'a str,
        /// The hand that moves it.
        hand: Hand,
    },
}

/// `count` different descriptions (fewer if the grammar has fewer) drawn from `phrasing`'s
/// phrasings; the first always names every hand the task uses (and, for pick and place, the
/// side), so a protocol can read what was asked from it.
pub fn describe(
    description: &Description<'_>,
    phrasing: Phrasing,
    count: usize,
    rng: &mut ChaCha8Rng,
) -> Vec<String> {
    let task = Task::of(description);
    let templates: Vec<&Template> =
        task.templates().iter().filter(|t| t.phrasing() == phrasing).collect();
    // Templates whose every filling names the hands (and the side) the task needs.
    let required = required_words(description);
    let complete: Vec<&Template> = templates
        .iter()
        .copied()
        .filter(|t| {
            let must = t.moods().iter().fold(None::<BTreeSet<String>>, |acc, &mood| {
                let vars = Vars::all(description, t, mood);
                let must = Grammar { vars: &vars, mood }.must(t.text, "h");
                Some(match acc {
                    None => must,
                    Some(acc) => acc.intersection(&must).cloned().collect(),
                })
            });
            must.is_some_and(|must| required.iter().all(|w| must.contains(*w)))
        })
        .collect();
    let mut texts: Vec<String> = Vec::with_capacity(count);
    // Draws that repeat an earlier text are retried; the bound stops a grammar with fewer
    // distinct texts than `count` from looping forever.
    let mut attempts = 64 + 64 * count;
    while texts.len() < count && attempts > 0 {
        attempts -= 1;
        let pool = if texts.is_empty() { &complete } else { &templates };
        if pool.is_empty() {
            break;
        }
        let template = pool[rng.random_range(0..pool.len())];
        let text = generate(description, template, rng);
        if !texts.contains(&text) {
            texts.push(text);
        }
    }
    texts
}

/// Every word (as [`words`] splits them) that `phrasing`'s grammar can produce, sorted, for
/// descriptions of catalogue objects.
pub fn grammar_words(phrasing: Phrasing) -> BTreeSet<String> {
    let mut set = BTreeSet::new();
    for task in Task::ALL {
        for template in task.templates().iter().filter(|t| t.phrasing() == phrasing) {
            for &mood in template.moods() {
                let vars = Vars::every(template, mood);
                Grammar { vars: &vars, mood }.walk(template.text, "h", &mut set);
            }
        }
    }
    set
}

/// The words of a text as the model's vocabulary splits them: lower-cased runs of
/// alphanumeric characters (the rule of `dex2hoi_model::text::words`, which this crate does
/// not depend on).
fn words(text: &str) -> Vec<String> {
    text.split(|c: char| !c.is_alphanumeric())
        .filter(|w| !w.is_empty())
        .map(str::to_lowercase)
        .collect()
}

/// The words the first description of a task must contain.
fn required_words(description: &Description<'_>) -> Vec<&'static str> {
    match *description {
        Description::PickPlace { hand, towards, .. } => vec![hand.word(), towards.word()],
        Description::Inspect { hand, .. } | Description::MoveNextTo { hand, .. } => {
            vec![hand.word()]
        }
        Description::LiftBoth { .. } | Description::Swap { .. } => vec!["hands"],
        Description::Handover { .. } | Description::HoldTwo { .. } | Description::Pour { .. } => {
            vec!["left", "right"]
        }
    }
}

/// Whether a sentence states what the person does or tells them to do it.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Mood {
    /// "The person picks up ...".
    Statement,
    /// "Pick up ...".
    Command,
}

/// The three fixed sentences of a task that the generator wrote before its grammar (dataset
/// format 2): 80 words in all, each task in the same three phrasings, the first naming every
/// hand (and, for pick and place, the side). `data synth --texts templates` trains on these in
/// place of the grammar's, so that a run can learn the tasks' words before their synonyms, or
/// tell what the grammar does to training.
pub fn template_sentences(description: &Description<'_>) -> Vec<String> {
    match *description {
        Description::PickPlace { object, hand, towards } => {
            let (hand, towards) = (hand.word(), towards.word());
            vec![
                format!(
                    "The person picks up the {object} with the {hand} hand and puts it down to the {towards}."
                ),
                format!(
                    "Using the {hand} hand, someone lifts the {object} and sets it down a little to the {towards}."
                ),
                format!("A person moves the {object} to the {towards} with the {hand} hand."),
            ]
        }
        Description::Inspect { object, hand } => {
            let hand = hand.word();
            vec![
                format!(
                    "The person picks up the {object} with the {hand} hand, turns it around to look at it and puts it back."
                ),
                format!(
                    "Someone inspects the {object} held in the {hand} hand and then returns it to the table."
                ),
                format!(
                    "A person lifts the {object} with the {hand} hand, examines it from several sides and sets it down."
                ),
            ]
        }
        Description::LiftBoth { object } => vec![
            format!("The person lifts the {object} with both hands and puts it back down."),
            format!(
                "Someone raises the {object} using both hands, holds it for a moment and lowers it again."
            ),
            format!("A person picks up the {object} with two hands and sets it back on the table."),
        ],
        Description::Handover { object, from } => {
            let (hand, other) = (from.word(), from.other().word());
            vec![
                format!(
                    "The person picks up the {object} with the {hand} hand, passes it to the {other} hand and puts it down on the {other} side."
                ),
                format!(
                    "Someone hands the {object} over from the {hand} hand to the {other} hand."
                ),
                format!(
                    "A person lifts the {object} with the {hand} hand, gives it to the other hand and places it to the {other}."
                ),
            ]
        }
        Description::HoldTwo { left, right } => vec![
            format!(
                "The person picks up the {left} with the left hand and the {right} with the right hand, holds both and puts them back."
            ),
            format!(
                "Someone lifts the {left} in the left hand and the {right} in the right hand at the same time and sets them down again."
            ),
            format!(
                "A person holds the {left} and the {right}, one in each hand, then returns them to the table."
            ),
        ],
        Description::Swap { left, right } => vec![
            format!("The person swaps the places of the {left} and the {right}."),
            format!(
                "Someone exchanges the positions of the {left} on the left and the {right} on the right."
            ),
            format!(
                "A person moves the {right} out of the way, puts the {left} in its place and the {right} where the {left} was."
            ),
        ],
        Description::Pour { pourer, receiver, hand } => {
            let (hand, other) = (hand.word(), hand.other().word());
            vec![
                format!(
                    "The person holds the {receiver} with the {other} hand and pours from the {pourer} with the {hand} hand."
                ),
                format!(
                    "Someone pours from the {pourer} into the {receiver}, steadying the {receiver} with the {other} hand."
                ),
                format!(
                    "A person lifts the {pourer} with the {hand} hand, tips it over the {receiver} and puts it back."
                ),
            ]
        }
        Description::MoveNextTo { moved, anchor, hand } => {
            let hand = hand.word();
            vec![
                format!("The person moves the {moved} next to the {anchor} with the {hand} hand."),
                format!("Using the {hand} hand, someone places the {moved} beside the {anchor}."),
                format!("A person picks up the {moved} and puts it down next to the {anchor}."),
            ]
        }
    }
}

/// The moods a template can be written in.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Moods {
    Both,
    Statement,
    Command,
}

/// One sentence template of a task.
#[derive(Debug, Clone, Copy)]
struct Template {
    text: &'static str,
    moods: Moods,
    held_out: bool,
}

impl Template {
    const fn phrasing(&self) -> Phrasing {
        if self.held_out { Phrasing::HeldOut } else { Phrasing::Training }
    }

    fn moods(&self) -> &'static [Mood] {
        match self.moods {
            Moods::Both => &[Mood::Statement, Mood::Command],
            Moods::Statement => &[Mood::Statement],
            Moods::Command => &[Mood::Command],
        }
    }

    fn has_subject(&self) -> bool {
        self.text.contains("{S}")
    }
}

/// A template with a subject slot, written in either mood.
const fn both(text: &'static str) -> Template {
    Template { text, moods: Moods::Both, held_out: false }
}

/// A statement (a subject, or a passive sentence with none).
const fn statement(text: &'static str) -> Template {
    Template { text, moods: Moods::Statement, held_out: false }
}

/// A command (imperative, often two sentences).
const fn command(text: &'static str) -> Template {
    Template { text, moods: Moods::Command, held_out: false }
}

/// The same template, held out of training.
const fn held_out(template: Template) -> Template {
    Template { held_out: true, ..template }
}

/// The task families, in the order of [`TEMPLATES`].
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Task {
    PickPlace,
    Inspect,
    LiftBoth,
    Handover,
    HoldTwo,
    Swap,
    Pour,
    MoveNextTo,
}

impl Task {
    const ALL: [Task; 8] = [
        Task::PickPlace,
        Task::Inspect,
        Task::LiftBoth,
        Task::Handover,
        Task::HoldTwo,
        Task::Swap,
        Task::Pour,
        Task::MoveNextTo,
    ];

    fn of(description: &Description<'_>) -> Task {
        match description {
            Description::PickPlace { .. } => Task::PickPlace,
            Description::Inspect { .. } => Task::Inspect,
            Description::LiftBoth { .. } => Task::LiftBoth,
            Description::Handover { .. } => Task::Handover,
            Description::HoldTwo { .. } => Task::HoldTwo,
            Description::Swap { .. } => Task::Swap,
            Description::Pour { .. } => Task::Pour,
            Description::MoveNextTo { .. } => Task::MoveNextTo,
        }
    }

    fn templates(self) -> &'static [Template] {
        TEMPLATES[self as usize]
    }
}

/// Variables of the templates: `S` subject, `poss` possessive, objects (see
/// [`description_values`]), `h` the acting hand, `o` the other hand, `d` the side an object goes
/// to, `l`/`r` the words left and right.
///
/// Sentence templates per task. Each template says only what is true of the task (see the
/// task's planner in `plan.rs`): which hand does what, where things go, that pick and place
/// moves an object only a little, that held objects are put back where they were.
const TEMPLATES: [&[Template]; 8] = [
    // Pick and place: the hand `h` lifts `obj` and puts it down a little towards `d`.
    &[
        both("{S} {adv} {pick} the {obj} {with:h} and {put_it} {towards:d}."),
        both("{S} {pick} the {obj} {from_table} {with:h}, then {put_it} {towards:d}."),
        both("Using {poss} {h} hand, {S} {adv} {move} the {obj} {towards:d}."),
        both("{S} {move} the {obj} {towards_any:d} {with_any:h}."),
        both("{S} {pick} the {obj} {in:h} and {put_it} {towards_any:d}."),
        both("{S} {pick} the {obj} and {put_it} {towards_any:d}."),
        both("{S} {adv} {move} the {obj} {towards_any:d}."),
        command("{pick} the {obj} {with:h}. {then_cap} {put_it} {towards:d}."),
        statement("The {obj} is {picked} {with:h} and {put_pp} {towards:d}."),
        held_out(both("With {poss} {h} hand, {S} {pick} the {obj} and {put_it} {towards:d}.")),
        held_out(both("{S} {move} the {obj} {from_table} {towards:d}, {using:h}.")),
    ],
    // Inspect: the hand `h` lifts `obj`, turns it to look at it, puts it back.
    &[
        both("{S} {pick} the {obj} {with:h}, {turn} to {look_inf} it and {put_back_it}."),
        both("{S} {examine} the {obj} {in:h} {from_sides} and then {put_back_it}."),
        both("{S} {pick} the {obj} {with:h}, {bring_up} and {turn}, then {put_back_it}."),
        both("{S} {pick} the {obj} {with:h}, {turning} to {look_inf} it from all sides."),
        held_out(both("{S} {examine} the {obj} {from_sides}, {turning} {in:h}.")),
        both("{S} {pick} the {obj} {from_table} to {look_inf} it and {put_back_it}."),
        both("{S} {adv} {examine} the {obj} {from_sides} and {put_back_it}."),
        command("{pick} the {obj} {with:h} and {turn}. {then_cap} {put_back_it}."),
        both(
            "{S} {pick} the {obj} {with:h} and {bring_up} to {look_inf} it {from_sides}, then {put_back_it}.",
        ),
        held_out(both(
            "Holding the {obj} {in:h}, {S} {examine} it {from_sides} before {putting_back_it}.",
        )),
        statement("The {obj} is {picked} {with:h}, {turned} and {put_back_pp}."),
    ],
    // Lift with both hands: `obj` is lifted, held a moment, put back.
    &[
        both("{S} {lift} the {obj} {both} and {put_back_it}."),
        both("{S} {lift} the {obj} {both}, {hold_moment} and {put_back_it}."),
        both(
            "Using both hands, {S} {lift} the {obj} {from_table}, {hold_moment}, then {put_back_it}.",
        ),
        both(
            "{S} {grip} the {obj} {by_sides} {both} and {lift_it} {up_a_bit}, then {put_back_it}.",
        ),
        both("{S} {lift} the {obj} {up_a_bit} and {put_back_it}."),
        both("{S} {lift} the {obj} {both_any} {up_a_bit}, then {put_back_it}."),
        command("{grip} the {obj} {both} and {lift_it} {up_a_bit}. {then_cap} {put_back_it}."),
        statement("The {obj} is {lifted} {both}, {held_pp} and {put_back_pp}."),
        both(
            "With both hands on {sides_of} the {obj}, {S} {lift_it} {up_a_bit} and {put_back_it}.",
        ),
        held_out(both(
            "{S} {adv} {lift} the {obj} {from_table}, {holding_it} {both}, and {put_back_it}.",
        )),
        held_out(both("{S} {grip} the {obj} {both}, then {lift_it} {up_a_bit} and {put_back_it}.")),
    ],
    // Handover: `h` picks `obj` up and passes it to `o`, which puts it down on its side.
    &[
        both("{S} {pick} the {obj} {with:h}, {pass} {poss} {o} hand and {put_it} {towards:o}."),
        both("{S} {hand_over} the {obj} from {poss} {h} hand to {poss} {o} hand {and_down:o}."),
        both("{S} {pick} the {obj} {with:h} and {pass} {other_hand}, which {puts_it} {towards:o}."),
        both(
            "Using {poss} {h} hand, {S} {pick} the {obj} and {pass} {poss} {o} hand, then {put_it} {towards:o}.",
        ),
        both("{S} {hand_over} the {obj} from one hand to the other and {put_it} {towards_any:o}."),
        both("{S} {pick} the {obj} {with:h} and {pass} {other_hand}."),
        command(
            "{pick} the {obj} {with:h}. {then_cap} {pass} {poss} {o} hand and {put_it} {towards:o}.",
        ),
        statement(
            "The {obj} is {picked} {with:h}, {passed} to the {o} hand and {put_pp} {towards:o}.",
        ),
        held_out(both(
            "After {pick_ing} the {obj} {with:h}, {S} {pass} {poss} {o} hand and {put_it} {towards:o}.",
        )),
        held_out(both("{S} {pass_obj} the {obj} to {other_hand} and {put_it} {towards_any:o}.")),
    ],
    // Hold two: `lobj` in the left hand, `robj` in the right, held up together, put back.
    // Each object and its hand stay in one clause (no comma or "and" between them), so a
    // reader never pairs an object with the wrong hand.
    &[
        both(
            "{S} {pick} the {lobj} {with:l} and the {robj} {with:r}, {hold_both} and {put_back_them}.",
        ),
        both(
            "{S} {pick} the {lobj} {in:l} and the {robj} {in:r} at the same time, then {put_back_them}.",
        ),
        both("{S} {pick} the {lobj} and the {robj}, one in each hand, and {put_back_them}."),
        both(
            "{S} {lift} the {lobj} {with:l} while {pick_ing} the {robj} {with:r}, then {put_back_them}.",
        ),
        both(
            "{S} {hold_up} the {lobj} {in:l} and the {robj} {in:r} {together}, then {put_back_them}.",
        ),
        both("{S} {lift} both the {lobj} and the {robj}, {hold_both} and {put_back_them}."),
        command("{pick} the {lobj} {with:l} and the {robj} {with:r}. {then_cap} {put_back_them}."),
        statement(
            "The {lobj} is {lifted} {with:l} and the {robj} {with:r}, and both are {put_back_pp}.",
        ),
        both(
            "Using {poss} left hand for the {lobj} and {poss} right hand for the {robj}, {S} {lift_them} {together} and {put_back_them}.",
        ),
        held_out(both(
            "With the {lobj} {in:l} and the {robj} {in:r}, {S} {hold_both} and {put_back_them}.",
        )),
        held_out(both(
            "{S} {hold_up} the {lobj} and the {robj} {together}, one in each hand, then {put_back_them}.",
        )),
    ],
    // Swap: `lobj` (on the left) and `robj` (on the right) trade places. The right hand moves
    // `robj` aside first, the left hand moves `lobj` to the right, the right hand brings `robj`
    // to the left.
    &[
        both("{S} {swap_places} the {places} of the {lobj} and the {robj} {both}."),
        both("{S} {swap_objs} the {lobj} on the left and the {robj} on the right {both}."),
        both(
            "{S} {swap_objs} the {lobj} and the {robj} so that the {lobj} {ends} on the right and the {robj} on the left.",
        ),
        both(
            "{S} {move} the {robj} out of the way {with:r}, {put} the {lobj} in its place {with:l} and {bring} the {robj} to where the {lobj} was.",
        ),
        both("{S} {swap_places} the {places} of the {lobj} and the {robj}."),
        statement("The {lobj} and the {robj} {trade}."),
        command(
            "{swap_objs} the {lobj} and the {robj} {both}. The {lobj} {goes} to the right and the {robj} to the left.",
        ),
        both("{S} {swap_objs} the {lobj} and the {robj}, {moving} the {robj} {aside} first."),
        held_out(both("Using both hands, {S} {swap_objs} the {lobj} and the {robj} {on_table}.")),
        held_out(both("{S} {swap_objs} the {lobj} on the left with the {robj} on the right.")),
    ],
    // Pour: `h` pours from `src` into `dst`, which `o` steadies.
    &[
        both("{S} {steady} the {dst} {with:o} and {pour_phrase} {with:h}."),
        both("{S} {pour_phrase} {with:h}, {steadying} the {dst} {with:o}."),
        both("{S} {pour_phrase}, {steadying} it {with:o}."),
        both(
            "While {steadying} the {dst} {in:o}, {S} {pick} the {src} {with:h}, {pour_it} into the {dst} and {put_back_it}.",
        ),
        both("{S} {pick} the {src} {with:h}, {pour_it} into the {dst} and {put_back_it}."),
        both("{S} {adv} {pour_phrase}."),
        both(
            "{S} {lift} the {src} {with:h} and {pour_it} into the {dst} before {putting_back_it}.",
        ),
        command("{steady} the {dst} {with:o}. {then_cap} {pour_phrase} {with:h}."),
        statement(
            "The {dst} is {held_pp_steady} {with:o} while the {src} is {poured_pp} {with:h}.",
        ),
        held_out(both(
            "Using {poss} {h} hand, {S} {pour_phrase} while {poss} {o} hand {steadies} it.",
        )),
        held_out(both(
            "{S} {pick} the {src} {with:h} and {pour_it} into the {dst}, which {poss} {o} hand {steadies}.",
        )),
    ],
    // Move next to: `h` puts `obj` down next to `ref`, on the `h` side of it.
    &[
        both("{S} {move} the {obj} {next_to} the {ref} {with:h}."),
        both("Using {poss} {h} hand, {S} {put} the {obj} {next_to} the {ref}."),
        both("{S} {pick} the {obj} and {put_it} {next_to} the {ref}."),
        both("{S} {pick} the {obj} {with:h} and {put_it} {side_of:h} the {ref}."),
        both("{S} {bring} the {obj} over to the {ref} {with:h} and {put_it} {next_to} it."),
        command("{pick} the {obj} {with:h}. {then_cap} {put_it} {next_to} the {ref}."),
        both("{S} {adv} {put} the {obj} {next_to} the {ref}."),
        both("{S} {move} the {obj} {with_any:h}, {putting_it} {side_of:h} the {ref}."),
        held_out(both(
            "With {poss} {h} hand, {S} {pick} the {obj} {from_table} and {put_it} {next_to} the {ref}.",
        )),
        held_out(statement("The {obj} is {moved_pp} {next_to} the {ref} {with:h}.")),
    ],
];

/// Shared synonym tables. An alternative `third|command` is a verb in the two moods.
const TABLES: &[(&str, &[&str])] = &[
    // Manner and order.
    (
        "adv",
        &[
            "",
            "slowly",
            "carefully",
            "gently",
            "calmly",
            "quickly",
            "steadily",
            "smoothly",
            "casually",
            "cautiously",
            "firmly",
            "briskly",
            "neatly",
            "deliberately",
            "patiently",
        ],
    ),
    (
        "then_cap",
        &[
            "Then",
            "After that,",
            "Next,",
            "Afterwards,",
            "Finally,",
            "Once that is done,",
            "Following that,",
        ],
    ),
    ("together", &["", "together", "at the same time", "simultaneously", "for a moment"]),
    // Scene.
    (
        "from_table",
        &[
            "",
            "from the table",
            "off the table",
            "from the tabletop",
            "from its spot on the table",
            "from the table surface",
        ],
    ),
    ("on_table", &["", "on the table", "on the tabletop"]),
    // Hands (`{side}`: the bound side word).
    (
        "with",
        &[
            "with {poss} {side} hand",
            "using {poss} {side} hand",
            "with the {side} hand",
            "using the {side} hand",
        ],
    ),
    ("using", &["using {poss} {side} hand", "using the {side} hand"]),
    ("in", &["in {poss} {side} hand", "in the {side} hand"]),
    ("with_any", &["{with}", "{side}-handed"]),
    (
        "other_hand",
        &["{poss} other hand", "the other hand", "{poss} free hand", "the opposite hand"],
    ),
    (
        "both",
        &[
            "with both hands",
            "using both hands",
            "with two hands",
            "with both hands at once",
            "in both hands",
        ],
    ),
    ("both_any", &["{both}", "two-handed"]),
    ("sides_of", &["either side of", "each side of", "the sides of"]),
    ("by_sides", &["", "by its sides", "by the sides", "from both sides"]),
    // Directions (`{side}`: where the object goes).
    (
        "towards",
        &[
            "to the {side}",
            "on the {side} side",
            "over to the {side}",
            "a bit further {side}",
            "a little to the {side}",
            "to {poss} {side}",
            "a bit to {poss} {side}",
            "on the {side}",
            "to its {side}",
            "further to the {side}",
            "a short way to the {side}",
            "to the {side} side of the table",
            "slightly to the {side}",
            "a little to the {side} of where it stood",
            "toward the {side}",
            "off to the {side}",
            "somewhat to the {side}",
            "over on the {side}",
        ],
    ),
    ("towards_any", &["{towards}", "{side}wards", "a bit {side}wards"]),
    ("side_of", &["to the {side} of", "on the {side} side of", "just to the {side} of"]),
    (
        "next_to",
        &[
            "next to",
            "beside",
            "close to",
            "near",
            "alongside",
            "by",
            "close beside",
            "just next to",
            "adjacent to",
            "side by side with",
        ],
    ),
    // Taking and putting.
    (
        "pick",
        &[
            "picks up|pick up",
            "grabs|grab",
            "takes|take",
            "lifts|lift",
            "grasps|grasp",
            "takes hold of|take hold of",
            "lifts up|lift up",
            "raises|raise",
            "reaches for and picks up|reach for and pick up",
        ],
    ),
    ("pick_ing", &["picking up", "grabbing", "taking", "lifting", "grasping", "raising"]),
    ("picked", &["picked up", "lifted", "taken", "grabbed", "raised"]),
    ("lift", &["lifts|lift", "raises|raise", "picks up|pick up", "lifts up|lift up"]),
    (
        "lift_it",
        &[
            "lifts it|lift it",
            "raises it|raise it",
            "picks it up|pick it up",
            "brings it up|bring it up",
        ],
    ),
    ("lifted", &["lifted", "raised", "picked up", "taken"]),
    ("grip", &["grips|grip", "grasps|grasp", "takes hold of|take hold of", "holds|hold"]),
    (
        "up_a_bit",
        &[
            "",
            "up",
            "off the table",
            "a little",
            "straight up",
            "into the air",
            "slightly",
            "a short distance",
        ],
    ),
    (
        "hold_moment",
        &[
            "holds it for a moment|hold it for a moment",
            "holds it up briefly|hold it up briefly",
            "keeps it in the air for a moment|keep it in the air for a moment",
            "holds it there for a second|hold it there for a second",
            "holds it up for a short while|hold it up for a short while",
        ],
    ),
    ("holding_it", &["holding it", "gripping it", "supporting it"]),
    (
        "held_pp",
        &[
            "held up for a moment",
            "held in the air briefly",
            "held there for a second",
            "kept up for a short while",
        ],
    ),
    (
        "hold_both",
        &[
            "holds both up|hold both up",
            "holds them up together|hold them up together",
            "holds them in the air|hold them in the air",
            "holds both for a moment|hold both for a moment",
            "keeps them up for a moment|keep them up for a moment",
        ],
    ),
    ("hold_up", &["holds up|hold up", "raises|raise", "lifts|lift", "picks up|pick up"]),
    (
        "put_it",
        &[
            "puts it down|put it down",
            "sets it down|set it down",
            "places it|place it",
            "puts it|put it",
            "leaves it|leave it",
            "rests it|rest it",
            "positions it|position it",
            "deposits it|deposit it",
            "sets it|set it",
            "places it down|place it down",
        ],
    ),
    ("putting_it", &["putting it down", "setting it down", "placing it"]),
    (
        "lift_them",
        &[
            "lifts them|lift them",
            "raises them|raise them",
            "picks them up|pick them up",
            "holds them up|hold them up",
        ],
    ),
    ("puts_it", &["puts it down", "sets it down", "places it"]),
    ("put_pp", &["put down", "set down", "placed", "moved", "carried", "brought"]),
    ("put", &["puts|put", "places|place", "sets|set", "sets down|set down", "puts down|put down"]),
    (
        "put_back_it",
        &[
            "puts it back|put it back",
            "puts it back down|put it back down",
            "sets it back down|set it back down",
            "returns it to the table|return it to the table",
            "places it back|place it back",
            "lowers it back down|lower it back down",
            "puts it back where it was|put it back where it was",
            "returns it to its place|return it to its place",
            "sets it back in its spot|set it back in its spot",
        ],
    ),
    (
        "putting_back_it",
        &[
            "putting it back",
            "returning it to the table",
            "setting it back down",
            "placing it back where it was",
            "lowering it back down",
        ],
    ),
    (
        "put_back_pp",
        &[
            "put back",
            "put back down",
            "set back down",
            "returned to the table",
            "placed back",
            "lowered back down",
        ],
    ),
    (
        "put_back_them",
        &[
            "puts them back|put them back",
            "puts them back down|put them back down",
            "sets them down|set them down",
            "returns them to the table|return them to the table",
            "lowers them back down|lower them back down",
            "places them back where they were|place them back where they were",
        ],
    ),
    (
        "move",
        &[
            "moves|move",
            "shifts|shift",
            "carries|carry",
            "relocates|relocate",
            "transfers|transfer",
            "brings|bring",
            "repositions|reposition",
            "takes|take",
        ],
    ),
    ("moved_pp", &["moved", "placed", "put", "set down", "carried", "brought"]),
    ("bring", &["brings|bring", "moves|move", "carries|carry", "puts|put"]),
    // Looking.
    (
        "examine",
        &[
            "looks at|look at",
            "inspects|inspect",
            "examines|examine",
            "checks|check",
            "studies|study",
            "looks over|look over",
            "takes a close look at|take a close look at",
            "has a look at|have a look at",
            "observes|observe",
            "scrutinizes|scrutinize",
        ],
    ),
    ("look_inf", &["look at", "inspect", "examine", "check", "study", "get a better look at"]),
    (
        "turn",
        &[
            "turns it around|turn it around",
            "turns it over|turn it over",
            "rotates it|rotate it",
            "turns it from side to side|turn it from side to side",
            "turns it one way and then the other|turn it one way and then the other",
            "tilts it|tilt it",
            "spins it around|spin it around",
            "twists it|twist it",
        ],
    ),
    (
        "turning",
        &["turning it around", "rotating it", "turning it over", "tilting it from side to side"],
    ),
    (
        "turned",
        &[
            "turned around",
            "turned over",
            "rotated",
            "inspected",
            "examined",
            "looked at",
            "checked",
        ],
    ),
    (
        "bring_up",
        &[
            "brings it up to {poss} chest|bring it up to {poss} chest",
            "holds it up in front of {poss} chest|hold it up in front of {poss} chest",
            "raises it to chest height|raise it to chest height",
            "brings it closer|bring it closer",
            "holds it up|hold it up",
        ],
    ),
    (
        "from_sides",
        &[
            "",
            "from several sides",
            "from different sides",
            "from all sides",
            "from every angle",
            "from a few angles",
            "in detail",
            "with interest",
            "curiously",
            "closely",
            "briefly",
        ],
    ),
    // Passing.
    (
        "pass",
        &[
            "passes it to|pass it to",
            "hands it over to|hand it over to",
            "hands it to|hand it to",
            "gives it to|give it to",
            "transfers it to|transfer it to",
            "moves it over to|move it over to",
        ],
    ),
    ("pass_obj", &["passes|pass", "hands|hand", "gives|give", "transfers|transfer"]),
    (
        "hand_over",
        &[
            "hands over|hand over",
            "passes|pass",
            "transfers|transfer",
            "moves|move",
            "shifts|shift",
        ],
    ),
    ("passed", &["passed", "handed over", "handed", "given", "transferred"]),
    ("and_down", &["", "and {put_it} {towards}"]),
    // Swapping.
    (
        "swap_objs",
        &[
            "swaps|swap",
            "exchanges|exchange",
            "switches|switch",
            "switches around|switch around",
            "interchanges|interchange",
        ],
    ),
    (
        "swap_places",
        &[
            "swaps|swap",
            "exchanges|exchange",
            "switches|switch",
            "trades|trade",
            "reverses|reverse",
        ],
    ),
    ("places", &["places", "positions", "spots", "locations"]),
    ("ends", &["ends up", "stands", "is"]),
    ("trade", &["trade places", "swap places", "switch places", "change places"]),
    ("goes", &["goes", "moves"]),
    ("moving", &["moving", "putting", "setting"]),
    ("aside", &["aside", "out of the way", "to one side"]),
    // Pouring (`src` poured from, `dst` poured into).
    (
        "pour_phrase",
        &[
            "pours from the {src} into the {dst}|pour from the {src} into the {dst}",
            "pours out of the {src} into the {dst}|pour out of the {src} into the {dst}",
            "empties the {src} into the {dst}|empty the {src} into the {dst}",
            "tips the {src} over the {dst}|tip the {src} over the {dst}",
            "tilts the {src} over the {dst}|tilt the {src} over the {dst}",
            "pours the contents of the {src} into the {dst}|pour the contents of the {src} into the {dst}",
        ],
    ),
    ("pour_it", &["tips it|tip it", "empties it|empty it", "pours it out|pour it out"]),
    (
        "steady",
        &[
            "holds|hold",
            "steadies|steady",
            "holds onto|hold onto",
            "grips|grip",
            "supports|support",
        ],
    ),
    ("steadying", &["holding", "steadying", "gripping", "holding onto", "supporting"]),
    ("steadies", &["holds", "steadies", "keeps still", "grips", "holds steady"]),
    ("held_pp_steady", &["held", "steadied", "held steady", "kept still", "supported"]),
    ("poured_pp", &["tipped over it", "emptied into it", "tilted over it", "poured out into it"]),
];

/// Third-person subjects and the possessive that goes with them.
const SUBJECTS: &[(&str, &str)] = &[
    ("the person", "their"),
    ("a person", "their"),
    ("someone", "their"),
    ("somebody", "their"),
    ("a man", "his"),
    ("the man", "his"),
    ("a young man", "his"),
    ("he", "his"),
    ("a woman", "her"),
    ("the woman", "her"),
    ("a young woman", "her"),
    ("she", "her"),
    ("a guy", "his"),
    ("a lady", "her"),
    ("an adult", "their"),
];

/// Names of each catalogue object in texts, the catalogue name first. "dish" is never used:
/// it could mean the bowl or the plate.
const OBJECTS: &[(&str, &[&str])] = &[
    ("mug", &["mug", "cup", "coffee mug", "coffee cup", "tea mug", "ceramic mug"]),
    ("bottle", &["bottle", "water bottle", "plastic bottle", "drink bottle", "glass bottle"]),
    ("box", &["box", "carton", "cardboard box", "package", "parcel", "storage box", "shoebox"]),
    ("ball", &["ball", "rubber ball", "toy ball", "little ball", "bouncy ball"]),
    ("bowl", &["bowl", "soup bowl", "cereal bowl", "salad bowl", "mixing bowl", "porcelain bowl"]),
    ("book", &["book", "hardcover book", "thick book", "novel", "textbook", "paperback book"]),
    ("can", &["can", "tin", "soda can", "tin can", "drinks can", "cola can", "beer can"]),
    ("plate", &["plate", "dinner plate", "flat plate", "ceramic plate"]),
];

/// How an object is named in texts: its synonyms (the catalogue name first), or just its name
/// if it is not in the catalogue.
pub fn synonyms(name: &str) -> Vec<String> {
    OBJECTS
        .iter()
        .find(|(n, _)| *n == name)
        .map_or_else(|| vec![name.to_string()], |(_, s)| s.iter().map(|s| s.to_string()).collect())
}

/// The values of the template variables: one each while generating a text, every possible
/// one while analysing the grammar.
#[derive(Debug, Clone, Default)]
struct Vars {
    entries: Vec<(&'static str, Vec<String>)>,
}

impl Vars {
    fn set(&mut self, name: &'static str, values: Vec<String>) {
        self.entries.push((name, values));
    }

    fn get(&self, name: &str) -> Option<&[String]> {
        self.entries.iter().find(|(n, _)| *n == name).map(|(_, v)| v.as_slice())
    }

    /// Every subject and possessive a template can be written with in `mood`.
    fn people(&mut self, template: &Template, mood: Mood) {
        let (subjects, possessives): (Vec<&str>, Vec<&str>) = match mood {
            Mood::Command => (vec![""], vec!["the", "your"]),
            // A passive statement has no subject to refer back to.
            Mood::Statement if !template.has_subject() => (vec![""], vec!["the"]),
            Mood::Statement => (
                SUBJECTS.iter().map(|(s, _)| *s).collect(),
                std::iter::once("the").chain(SUBJECTS.iter().map(|(_, p)| *p)).collect(),
            ),
        };
        let owned = |v: Vec<&str>| {
            let set: BTreeSet<String> = v.into_iter().map(str::to_string).collect();
            set.into_iter().collect()
        };
        self.set("S", owned(subjects));
        self.set("poss", owned(possessives));
    }

    fn sides(&mut self) {
        self.set("l", vec!["left".into()]);
        self.set("r", vec!["right".into()]);
    }

    /// Every value the variables of `description` can take in `template` and `mood`.
    fn all(description: &Description<'_>, template: &Template, mood: Mood) -> Vars {
        let mut vars = Vars::default();
        vars.people(template, mood);
        vars.sides();
        for (name, value) in description_values(description) {
            let values = match value {
                Value::Object(object) => synonyms(object),
                Value::Side(hand) => vec![hand.word().to_string()],
            };
            vars.set(name, values);
        }
        vars
    }

    /// Every value any description of catalogue objects gives the variables.
    fn every(template: &Template, mood: Mood) -> Vars {
        let mut vars = Vars::default();
        vars.people(template, mood);
        vars.sides();
        let objects: Vec<String> =
            OBJECTS.iter().flat_map(|(_, s)| s.iter().map(|s| s.to_string())).collect();
        for name in ["obj", "ref", "src", "dst", "lobj", "robj"] {
            vars.set(name, objects.clone());
        }
        for name in ["h", "o", "d"] {
            vars.set(name, vec!["left".into(), "right".into()]);
        }
        vars
    }
}

/// A value of a description.
#[derive(Debug, Clone, Copy)]
enum Value<'a> {
    Object(&'a str),
    Side(Hand),
}

/// The variables of a description and their values.
fn description_values<'a>(description: &Description<'a>) -> Vec<(&'static str, Value<'a>)> {
    use Value::{Object, Side};
    match *description {
        Description::PickPlace { object, hand, towards } => {
            vec![
                ("obj", Object(object)),
                ("h", Side(hand)),
                ("o", Side(hand.other())),
                ("d", Side(towards)),
            ]
        }
        Description::Inspect { object, hand } => {
            vec![("obj", Object(object)), ("h", Side(hand)), ("o", Side(hand.other()))]
        }
        Description::LiftBoth { object } => vec![("obj", Object(object))],
        Description::Handover { object, from } => {
            vec![("obj", Object(object)), ("h", Side(from)), ("o", Side(from.other()))]
        }
        Description::HoldTwo { left, right } | Description::Swap { left, right } => {
            vec![("lobj", Object(left)), ("robj", Object(right))]
        }
        Description::Pour { pourer, receiver, hand } => vec![
            ("src", Object(pourer)),
            ("dst", Object(receiver)),
            ("h", Side(hand)),
            ("o", Side(hand.other())),
        ],
        Description::MoveNextTo { moved, anchor, hand } => vec![
            ("obj", Object(moved)),
            ("ref", Object(anchor)),
            ("h", Side(hand)),
            ("o", Side(hand.other())),
        ],
    }
}

/// One text of `template`: a mood, a subject and object names drawn once, then the slots.
fn generate(description: &Description<'_>, template: &Template, rng: &mut ChaCha8Rng) -> String {
    let moods = template.moods();
    // Commands are the rarer register in the texts people write about motion.
    let mood = if moods.len() == 2 {
        if rng.random_bool(0.3) { Mood::Command } else { Mood::Statement }
    } else {
        moods[0]
    };
    let all = Vars::all(description, template, mood);
    let mut vars = Vars::default();
    match mood {
        Mood::Statement if template.has_subject() => {
            let (subject, possessive) = SUBJECTS[rng.random_range(0..SUBJECTS.len())];
            let possessive = if rng.random_bool(0.5) { possessive } else { "the" };
            vars.set("S", vec![subject.into()]);
            vars.set("poss", vec![possessive.into()]);
        }
        _ => {
            for name in ["S", "poss"] {
                let values = all.get(name).unwrap_or_default();
                vars.set(name, pick_one(values, rng));
            }
        }
    }
    for (name, values) in &all.entries {
        if vars.get(name).is_none() {
            vars.set(name, pick_one(values, rng));
        }
    }
    let mut raw = String::new();
    Grammar { vars: &vars, mood }.fill(template.text, "h", rng, &mut raw);
    tidy(&raw)
}

fn pick_one(values: &[String], rng: &mut ChaCha8Rng) -> Vec<String> {
    if values.is_empty() {
        return Vec::new();
    }
    vec![values[rng.random_range(0..values.len())].clone()]
}

/// Single spaces, none before punctuation (empty slots leave gaps), a capital first letter.
fn tidy(raw: &str) -> String {
    let mut text = raw.split_whitespace().collect::<Vec<_>>().join(" ");
    for punctuation in [",", "."] {
        text = text.replace(&format!(" {punctuation}"), punctuation);
    }
    let mut chars = text.chars();
    match chars.next() {
        Some(first) => first.to_uppercase().chain(chars).collect(),
        None => text,
    }
}

/// A part of a template: literal text or a slot (the text between the braces).
#[derive(Debug, Clone, Copy, PartialEq)]
enum Part<'t> {
    Literal(&'t str),
    Slot(&'t str),
}

/// The parts of a template.
///
/// Panics on an unclosed brace: templates are constants of this module, and a test parses
/// every one.
fn parts(text: &str) -> Vec<Part<'_>> {
    let mut parts = Vec::new();
    let mut rest = text;
    while let Some(open) = rest.find('{') {
        if open > 0 {
            parts.push(Part::Literal(&rest[..open]));
        }
        let close = rest[open..].find('}').map(|c| open + c);
        let close = close.unwrap_or_else(|| panic!("unclosed slot in template {text:?}"));
        parts.push(Part::Slot(&rest[open + 1..close]));
        rest = &rest[close + 1..];
    }
    if !rest.is_empty() {
        parts.push(Part::Literal(rest));
    }
    parts
}

/// Whether a slot at `index` is glued to a word of the literal beside it ("{side}wards"): its
/// words then are not words of their own.
fn glued(parts: &[Part<'_>], index: usize) -> bool {
    let before = index.checked_sub(1).and_then(|i| match parts[i] {
        Part::Literal(l) => l.chars().next_back(),
        Part::Slot(_) => None,
    });
    let after = parts.get(index + 1).and_then(|p| match p {
        Part::Literal(l) => l.chars().next(),
        Part::Slot(_) => None,
    });
    before.is_some_and(char::is_alphanumeric) || after.is_some_and(char::is_alphanumeric)
}

/// The grammar with bound variables in one mood.
struct Grammar<'v> {
    vars: &'v Vars,
    mood: Mood,
}

impl Grammar<'_> {
    /// The alternatives of a slot and the side variable its `{side}` slots refer to.
    ///
    /// Panics on an unknown slot name: templates and tables are constants of this module, and a
    /// test walks every slot of every template.
    fn alternatives<'a>(
        &'a self,
        slot: &'a str,
        side: &'static str,
    ) -> (Vec<&'a str>, &'static str) {
        if slot.contains('|') {
            return (vec![self.conjugate(slot)], side);
        }
        let (name, side) = match slot.split_once(':') {
            Some((name, var)) => (name, side_var(var)),
            None => (slot, side),
        };
        let name = if name == "side" { side } else { name };
        if let Some(values) = self.vars.get(name) {
            return (values.iter().map(String::as_str).collect(), side);
        }
        match TABLES.iter().find(|(n, _)| *n == name) {
            Some((_, alternatives)) => {
                (alternatives.iter().map(|a| self.conjugate(a)).collect(), side)
            }
            None => panic!("unknown slot {slot:?} in the description grammar"),
        }
    }

    /// The form of a `third|command` alternative in this grammar's mood.
    fn conjugate<'a>(&self, alternative: &'a str) -> &'a str {
        match alternative.split_once('|') {
            Some((third, command)) => match self.mood {
                Mood::Statement => third,
                Mood::Command => command,
            },
            None => alternative,
        }
    }

    /// Fills `text` with random alternatives.
    fn fill(&self, text: &str, side: &'static str, rng: &mut ChaCha8Rng, out: &mut String) {
        for part in parts(text) {
            match part {
                Part::Literal(literal) => out.push_str(literal),
                Part::Slot(slot) => {
                    let (alternatives, side) = self.alternatives(slot, side);
                    if !alternatives.is_empty() {
                        let chosen = alternatives[rng.random_range(0..alternatives.len())];
                        self.fill(chosen, side, rng, out);
                    }
                }
            }
        }
    }

    /// Every full filling of `text` (only used on the small slots glued to a word).
    fn expansions(&self, text: &str, side: &'static str) -> Vec<String> {
        let mut results = vec![String::new()];
        for part in parts(text) {
            results = match part {
                Part::Literal(literal) => results.into_iter().map(|r| r + literal).collect(),
                Part::Slot(slot) => {
                    let (alternatives, side) = self.alternatives(slot, side);
                    let tails: Vec<String> =
                        alternatives.iter().flat_map(|a| self.expansions(a, side)).collect();
                    results
                        .iter()
                        .flat_map(|r| tails.iter().map(move |t| format!("{r}{t}")))
                        .collect()
                }
            };
        }
        results
    }

    /// The template with its first glued slot replaced by each of its fillings, if it has one.
    fn unglue(&self, text: &str, side: &'static str) -> Option<Vec<String>> {
        let parts = parts(text);
        let index =
            (0..parts.len()).find(|&i| matches!(parts[i], Part::Slot(_)) && glued(&parts, i))?;
        let Part::Slot(slot) = parts[index] else { return None };
        let (alternatives, inner) = self.alternatives(slot, side);
        let fillings: Vec<String> =
            alternatives.iter().flat_map(|a| self.expansions(a, inner)).collect();
        let source = |p: &Part<'_>| match *p {
            Part::Literal(l) => l.to_string(),
            Part::Slot(s) => format!("{{{s}}}"),
        };
        let before: String = parts[..index].iter().map(source).collect();
        let after: String = parts[index + 1..].iter().map(source).collect();
        Some(fillings.into_iter().map(|f| format!("{before}{f}{after}")).collect())
    }

    /// Adds every word a filling of `text` can contain to `set`.
    fn walk(&self, text: &str, side: &'static str, set: &mut BTreeSet<String>) {
        if let Some(texts) = self.unglue(text, side) {
            for text in texts {
                self.walk(&text, side, set);
            }
            return;
        }
        for part in parts(text) {
            match part {
                Part::Literal(literal) => set.extend(words(literal)),
                Part::Slot(slot) => {
                    let (alternatives, side) = self.alternatives(slot, side);
                    for alternative in alternatives {
                        self.walk(alternative, side, set);
                    }
                }
            }
        }
    }

    /// The words every filling of `text` contains.
    fn must(&self, text: &str, side: &'static str) -> BTreeSet<String> {
        if let Some(texts) = self.unglue(text, side) {
            return intersection(texts.iter().map(|t| self.must(t, side)));
        }
        let mut set = BTreeSet::new();
        for part in parts(text) {
            match part {
                Part::Literal(literal) => set.extend(words(literal)),
                Part::Slot(slot) => {
                    let (alternatives, side) = self.alternatives(slot, side);
                    set.extend(intersection(alternatives.iter().map(|a| self.must(a, side))));
                }
            }
        }
        set
    }
}

/// The words in all of the sets (none if there are no sets).
fn intersection(sets: impl Iterator<Item = BTreeSet<String>>) -> BTreeSet<String> {
    sets.reduce(|a, b| a.intersection(&b).cloned().collect()).unwrap_or_default()
}

/// The variable a `{name:var}` slot binds `{side}` to.
///
/// Panics on an unknown variable: templates are constants of this module, and a test walks
/// every slot of every template.
fn side_var(var: &str) -> &'static str {
    match var {
        "h" => "h",
        "o" => "o",
        "d" => "d",
        "l" => "l",
        "r" => "r",
        _ => panic!("unknown side variable {var:?} in the description grammar"),
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::SeedableRng;
    use std::collections::HashSet;

    use dex2hoi_data::catalogue::CATALOGUE;

    /// The rest of a template after a slot, for the derivation search.
    struct Cont<'a> {
        text: &'a str,
        side: &'static str,
        next: Option<&'a Cont<'a>>,
    }

    /// Whether `grammar` derives `target` (lower-cased, tidied) from `text` followed by `next`.
    /// A space of a template matches one space or none, as tidying removes the gaps empty
    /// slots leave; this can only accept more texts than the grammar makes, which makes the
    /// held-out check stricter.
    fn derives(
        grammar: &Grammar<'_>,
        target: &[u8],
        pos: usize,
        text: &str,
        side: &'static str,
        next: Option<&Cont<'_>>,
    ) -> bool {
        let Some(&byte) = text.as_bytes().first() else {
            return match next {
                None => pos == target.len(),
                Some(cont) => derives(grammar, target, pos, cont.text, cont.side, cont.next),
            };
        };
        match byte {
            b'{' => {
                let close = text.find('}').unwrap();
                let cont = Cont { text: &text[close + 1..], side, next };
                let (alternatives, inner) = grammar.alternatives(&text[1..close], side);
                alternatives.iter().any(|a| derives(grammar, target, pos, a, inner, Some(&cont)))
            }
            b' ' => {
                (target.get(pos) == Some(&b' ')
                    && derives(grammar, target, pos + 1, &text[1..], side, next))
                    || derives(grammar, target, pos, &text[1..], side, next)
            }
            _ => {
                target.get(pos).is_some_and(|t| t.eq_ignore_ascii_case(&byte))
                    && derives(grammar, target, pos + 1, &text[1..], side, next)
            }
        }
    }

    /// Whether any `phrasing` template of the task can produce `text`.
    fn producible(description: &Description<'_>, phrasing: Phrasing, text: &str) -> bool {
        let target = text.to_lowercase();
        Task::of(description).templates().iter().filter(|t| t.phrasing() == phrasing).any(|t| {
            t.moods().iter().any(|&mood| {
                let vars = Vars::all(description, t, mood);
                let grammar = Grammar { vars: &vars, mood };
                derives(&grammar, target.as_bytes(), 0, t.text, "h", None)
            })
        })
    }

    const NAMES: [&str; 8] = ["mug", "bottle", "box", "ball", "bowl", "book", "can", "plate"];

    /// Every description of catalogue objects: each task, object (pairs distinct), hand, side.
    fn all_descriptions() -> Vec<Description<'static>> {
        let mut all = Vec::new();
        for a in NAMES {
            all.push(Description::LiftBoth { object: a });
            for hand in Hand::BOTH {
                all.push(Description::Inspect { object: a, hand });
                all.push(Description::Handover { object: a, from: hand });
                for towards in Hand::BOTH {
                    all.push(Description::PickPlace { object: a, hand, towards });
                }
            }
            for b in NAMES.into_iter().filter(|b| *b != a) {
                all.push(Description::HoldTwo { left: a, right: b });
                all.push(Description::Swap { left: a, right: b });
                for hand in Hand::BOTH {
                    all.push(Description::Pour { pourer: a, receiver: b, hand });
                    all.push(Description::MoveNextTo { moved: a, anchor: b, hand });
                }
            }
        }
        all
    }

    fn objects<'a>(description: &Description<'a>) -> Vec<&'a str> {
        description_values(description)
            .into_iter()
            .filter_map(|(_, v)| match v {
                Value::Object(o) => Some(o),
                Value::Side(_) => None,
            })
            .collect()
    }

    /// Whether `phrase`'s words occur in a row in `words`.
    fn contains_phrase(text_words: &[String], phrase: &str) -> bool {
        let phrase = words(phrase);
        text_words.windows(phrase.len()).any(|w| w == phrase.as_slice())
    }

    fn mentions(words: &[String], object: &str) -> bool {
        synonyms(object).iter().any(|s| contains_phrase(words, s))
    }

    /// The last word of each name of an object: what makes a phrase name it.
    fn head_words(object: &str) -> Vec<String> {
        synonyms(object).iter().map(|s| words(s).pop().unwrap()).collect()
    }

    /// Clauses of a text: split at punctuation and conjunctions.
    fn clauses(text: &str) -> Vec<Vec<String>> {
        let mut text = text.to_lowercase().replace([',', '.', ':'], " | ");
        for conjunction in [" and ", " while ", " then "] {
            text = text.replace(conjunction, " | ");
        }
        text.split('|').map(words).filter(|w| !w.is_empty()).collect()
    }

    #[test]
    fn words_follow_the_documented_rule() {
        assert_eq!(
            words("Pick up the mug, right-handed."),
            ["pick", "up", "the", "mug", "right", "handed"]
        );
        assert_eq!(words("  The Person's CUP2  "), ["the", "person", "s", "cup2"]);
        assert!(words(" ,.- ").is_empty());
    }

    #[test]
    fn the_catalogue_names_are_the_object_tables() {
        let catalogue: Vec<&str> = CATALOGUE.iter().map(|o| o.name).collect();
        assert_eq!(catalogue, NAMES);
        for (name, names) in OBJECTS {
            assert_eq!(names[0], *name);
            assert!(names.iter().all(|n| !words(n).contains(&"dish".to_string())));
        }
        // No name of one object is a word of another's names.
        for (a, _) in OBJECTS {
            for (b, names) in OBJECTS.iter().filter(|(b, _)| b != a) {
                for head in head_words(a) {
                    assert!(names.iter().all(|n| !words(n).contains(&head)), "{head} in {b}");
                }
            }
        }
    }

    #[test]
    fn vocabulary_is_large_and_held_out_words_are_trained() {
        let training = grammar_words(Phrasing::Training);
        let held_out = grammar_words(Phrasing::HeldOut);
        assert!(training.len() >= 300, "{} training words", training.len());
        let unknown: Vec<&String> = held_out.difference(&training).collect();
        assert!(unknown.is_empty(), "held-out words missing from training: {unknown:?}");
        for everyday in ["grab", "cup", "take", "set", "place", "your", "side", "carefully"] {
            assert!(training.contains(everyday), "{everyday}");
        }
        for banned in ["again", "twice", "repeatedly", "repeat", "dish", "slides"] {
            assert!(!training.contains(banned), "{banned}");
        }
    }

    #[test]
    fn grammar_words_are_exactly_the_words_drawn() {
        for phrasing in [Phrasing::Training, Phrasing::HeldOut] {
            let mut drawn = BTreeSet::new();
            let mut rng = ChaCha8Rng::seed_from_u64(7);
            for description in all_descriptions() {
                for text in describe(&description, phrasing, 40, &mut rng) {
                    drawn.extend(words(&text));
                }
            }
            let grammar = grammar_words(phrasing);
            let extra: Vec<&String> = drawn.difference(&grammar).collect();
            assert!(extra.is_empty(), "{phrasing:?} drew words outside grammar_words: {extra:?}");
            let missing: Vec<&String> = grammar.difference(&drawn).collect();
            assert!(missing.is_empty(), "{phrasing:?} never drew {missing:?}");
        }
    }

    #[test]
    fn about_a_fifth_of_each_tasks_templates_are_held_out() {
        for task in Task::ALL {
            let templates = task.templates();
            let held: Vec<&str> = templates.iter().filter(|t| t.held_out).map(|t| t.text).collect();
            let fraction = held.len() as f32 / templates.len() as f32;
            assert!((0.15..=0.3).contains(&fraction), "{task:?}: {fraction}");
            // Structurally disjoint: no template is both.
            for t in templates.iter().filter(|t| !t.held_out) {
                assert!(!held.contains(&t.text), "{task:?}: {}", t.text);
            }
        }
    }

    #[test]
    fn every_description_has_complete_templates_in_both_phrasings() {
        for description in all_descriptions() {
            for phrasing in [Phrasing::Training, Phrasing::HeldOut] {
                let mut rng = ChaCha8Rng::seed_from_u64(1);
                let texts = describe(&description, phrasing, 1, &mut rng);
                assert_eq!(texts.len(), 1, "{description:?} {phrasing:?}");
            }
        }
    }

    #[test]
    fn held_out_sentences_are_never_training_sentences() {
        let mut rng = ChaCha8Rng::seed_from_u64(11);
        for description in all_descriptions() {
            for text in describe(&description, Phrasing::HeldOut, 12, &mut rng) {
                assert!(
                    !producible(&description, Phrasing::Training, &text),
                    "training derives held-out {text:?}"
                );
                assert!(producible(&description, Phrasing::HeldOut, &text), "{text:?}");
            }
            for text in describe(&description, Phrasing::Training, 4, &mut rng) {
                assert!(!producible(&description, Phrasing::HeldOut, &text), "{text:?}");
                assert!(producible(&description, Phrasing::Training, &text), "{text:?}");
            }
        }
        // And by plain comparison of many draws, one description of each task.
        let samples = [
            Description::PickPlace { object: "mug", hand: Hand::Right, towards: Hand::Left },
            Description::Inspect { object: "can", hand: Hand::Left },
            Description::LiftBoth { object: "box" },
            Description::Handover { object: "ball", from: Hand::Right },
            Description::HoldTwo { left: "mug", right: "bottle" },
            Description::Swap { left: "bowl", right: "can" },
            Description::Pour { pourer: "bottle", receiver: "bowl", hand: Hand::Left },
            Description::MoveNextTo { moved: "can", anchor: "mug", hand: Hand::Right },
        ];
        for description in samples {
            let draw = |phrasing, seed| {
                let mut set = HashSet::new();
                for seed in seed..seed + 200 {
                    let mut rng = ChaCha8Rng::seed_from_u64(seed);
                    set.extend(describe(&description, phrasing, 10, &mut rng));
                }
                set
            };
            let training = draw(Phrasing::Training, 0);
            let held_out = draw(Phrasing::HeldOut, 1000);
            assert!(training.len() > 1000 && held_out.len() > 500);
            assert!(training.is_disjoint(&held_out), "{description:?}");
        }
    }

    #[test]
    fn descriptions_are_true_of_their_task() {
        let banned = ["again", "twice", "repeatedly", "dish"];
        for seed in 0..500u64 {
            let mut rng = ChaCha8Rng::seed_from_u64(seed);
            let all = all_descriptions();
            let description = all[rng.random_range(0..all.len())];
            for phrasing in [Phrasing::Training, Phrasing::HeldOut] {
                let texts = describe(&description, phrasing, 6, &mut rng);
                // The same seed gives the same texts.
                let draw = |seed| {
                    describe(&description, phrasing, 6, &mut ChaCha8Rng::seed_from_u64(seed))
                };
                assert_eq!(draw(seed + 1000), draw(seed + 1000), "deterministic");
                assert_eq!(texts.len(), 6);
                let distinct: HashSet<&String> = texts.iter().collect();
                assert_eq!(distinct.len(), texts.len());
                let named = objects(&description);
                for (i, text) in texts.iter().enumerate() {
                    let w = words(text);
                    let context = format!("{description:?} {phrasing:?}: {text:?}");
                    assert!(text.chars().next().is_some_and(char::is_uppercase), "{context}");
                    assert!(
                        text.ends_with('.') && !text.contains(" .") && !text.contains("  "),
                        "{context}"
                    );
                    for sentence in text.split(". ") {
                        assert!(
                            sentence.chars().next().is_some_and(char::is_uppercase),
                            "{context}"
                        );
                    }
                    assert!(
                        w.iter().all(|w| !banned.contains(&w.as_str()) && !w.starts_with("repeat")),
                        "{context}"
                    );
                    for object in &named {
                        assert!(mentions(&w, object), "{object} unnamed: {context}");
                    }
                    for other in NAMES.iter().filter(|n| !named.contains(n)) {
                        for head in head_words(other) {
                            assert!(!w.contains(&head), "{other} named: {context}");
                        }
                    }
                    let has = |word: &str| w.iter().any(|x| x == word);
                    let sides: Vec<&str> =
                        ["left", "right"].into_iter().filter(|s| has(s)).collect();
                    match description {
                        Description::PickPlace { hand, towards, .. } => {
                            assert!(
                                sides.iter().all(|s| *s == hand.word() || *s == towards.word()),
                                "{context}"
                            );
                            if i == 0 {
                                assert!(
                                    has(hand.word()) && has(towards.word()) && has("hand")
                                        || has("handed"),
                                    "{context}"
                                );
                                assert!(has(hand.word()) && has(towards.word()), "{context}");
                            }
                        }
                        Description::Inspect { hand, .. }
                        | Description::MoveNextTo { hand, .. } => {
                            assert!(sides.iter().all(|s| *s == hand.word()), "{context}");
                            if i == 0 {
                                assert!(has(hand.word()), "{context}");
                            }
                        }
                        Description::LiftBoth { .. } => {
                            assert!(sides.is_empty(), "{context}");
                            if i == 0 {
                                let both = ["both", "two", "either", "each"];
                                assert!(has("hands") && both.iter().any(|w| has(w)), "{context}");
                            }
                        }
                        Description::Swap { .. } => {
                            if i == 0 {
                                assert!(has("hands") && (has("both") || has("two")), "{context}");
                            }
                        }
                        Description::Handover { .. } => {
                            if i == 0 {
                                assert!(has("left") && has("right"), "{context}");
                            }
                        }
                        Description::HoldTwo { left, right } => {
                            let mut paired = false;
                            for clause in clauses(text) {
                                let h = |s: &str| clause.iter().any(|x| x == s);
                                if mentions(&clause, left) {
                                    assert!(
                                        !h("right"),
                                        "left object with the right hand: {context}"
                                    );
                                    paired |= h("left");
                                }
                                if mentions(&clause, right) {
                                    assert!(
                                        !h("left"),
                                        "right object with the left hand: {context}"
                                    );
                                }
                            }
                            if i == 0 {
                                assert!(paired && has("right"), "{context}");
                            }
                        }
                        Description::Pour { pourer, receiver, hand } => {
                            for clause in clauses(text) {
                                let h = |s: &str| clause.iter().any(|x| x == s);
                                let expected = if mentions(&clause, pourer) {
                                    hand
                                } else if mentions(&clause, receiver) {
                                    hand.other()
                                } else {
                                    continue;
                                };
                                assert!(!h(expected.other().word()), "wrong hand: {context}");
                            }
                            if i == 0 {
                                assert!(has("left") && has("right"), "{context}");
                            }
                        }
                    }
                }
            }
        }
    }

    #[test]
    fn fewer_texts_when_the_grammar_runs_out() {
        let description = Description::Swap { left: "mug", right: "ball" };
        let mut rng = ChaCha8Rng::seed_from_u64(3);
        assert!(describe(&description, Phrasing::Training, 0, &mut rng).is_empty());
        // An unknown object is named as it is, without synonyms.
        let texts =
            describe(&Description::LiftBoth { object: "crate" }, Phrasing::Training, 5, &mut rng);
        assert_eq!(texts.len(), 5);
        assert!(texts.iter().all(|t| words(t).contains(&"crate".to_string())));
    }
}
