# Public benchmarks: for campaigns with an `import:` entry in the config, convert
# the benchmark's files into an mbst campaign (`mbst import FORMAT DATA_DIR`).
# `mbst import` writes atomically; --overwrite replaces a campaign of older code.


rule import_campaign:
    output:
        campaign=directory("results/{campaign}/import/campaign"),
    log:
        "logs/import/{campaign}.log",
    wildcard_constraints:
        campaign=alternation(IMPORT_CAMPAIGNS),
    params:
        fmt=lambda wildcards: campaign_entry(wildcards)["import"]["format"],
        data_dir=lambda wildcards: campaign_entry(wildcards)["import"]["data_dir"],
        control=import_control_args,
        code=CODE_VERSION,
    conda:
        "../envs/mbst.yaml"
    shell:
        "mbst import {params.fmt} {params.data_dir:q} {params.control} --out {output.campaign:q}"
        " --overwrite"
        " > {log:q} 2>&1"
