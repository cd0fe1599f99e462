"""Tables of the methods and the examples, written at build time from what each describes
of itself (`nhjax._methods`, `nhjax.examples.EXAMPLES`), where a page says
`<!-- methods -->` or `<!-- examples -->`."""


def _methods_table() -> str:
    from nhjax._methods import description, integrates_adapted, is_symmetric, keeps_constraint, keeps_energy, METHODS

    rows = [
        "| command-line name | method | order | symmetric | energy | constraint | system form |",
        "|---|---|---|---|---|---|---|",
    ]
    for name, method in METHODS.items():
        solver = method.solver
        rows.append(
            f"| `{name}` | {method.name} | {solver.order(None)} | {'yes' if is_symmetric(solver) else 'no'} | "
            f"{'to roundoff' if keeps_energy(solver) else 'no'} | "
            f"{'to roundoff' if keeps_constraint(solver) else 'no'} | "
            f"{'adapted' if integrates_adapted(solver) else 'canonical'} |"
        )
    notes = "\n".join(f"- **{method.name}**: {description(method.solver)}." for method in METHODS.values())
    return "\n".join(rows) + "\n\n" + notes + "\n"


def _examples_table() -> str:
    from nhjax.examples import EXAMPLES

    rows = ["| name | class | forms | parameters | start (`initial_state`) |", "|---|---|---|---|---|"]
    for name, example in EXAMPLES.items():
        made = example()
        parameters = ", ".join(f"{key} = {value}" for key, value in made.parameters().items()) or "none"
        start = ", ".join(f"{key} = {value}" for key, value in made.initial_state_choices().items())
        rows.append(
            f"| `{name}` | `nhjax.examples.{example.__name__}` | {', '.join(made.forms())} | {parameters} | {start} |"
        )
    return "\n".join(rows) + "\n"


def on_page_markdown(markdown, page, config, files):
    if "<!-- methods -->" in markdown:
        markdown = markdown.replace("<!-- methods -->", _methods_table())
    if "<!-- examples -->" in markdown:
        markdown = markdown.replace("<!-- examples -->", _examples_table())
    return markdown
