// Validates glTF files with the Khronos glTF validator (pinned in package-lock.json) and fails on
// any error. Warnings, infos and hints are printed but pass: the exporter's contract is "no
// errors" (docs/export.md).
//
//   npm ci --prefix tools/gltf-validator
//   node tools/gltf-validator/validate.mjs avatar.glb [more.glb ...]
//
// Exit status: 0 when no file has an error, 1 when one has, 2 on a usage or read failure.

import { readFile } from 'node:fs/promises';
import { basename } from 'node:path';
import validator from 'gltf-validator';

const files = process.argv.slice(2);
if (files.length === 0) {
    console.error('usage: node validate.mjs FILE.glb [FILE.glb ...]');
    process.exit(2);
}

// Enough lines to see what is wrong without flooding a CI log with one issue repeated per vertex.
const SHOWN_PER_SEVERITY = 20;
const SEVERITY = ['error', 'warning', 'info', 'hint'];

let failed = false;
for (const file of files) {
    let bytes;
    try {
        bytes = new Uint8Array(await readFile(file));
    } catch (e) {
        console.error(`${file}: cannot read: ${e.message}`);
        process.exit(2);
    }
    let report;
    try {
        report = await validator.validateBytes(bytes, {
            uri: basename(file),
            maxIssues: 0, // count every issue, so the totals are true
            writeTimestamp: false,
        });
    } catch (e) {
        console.error(`${file}: the validator could not read it: ${e}`);
        process.exit(2);
    }
    const { numErrors, numWarnings, numInfos, numHints, messages } = report.issues;
    const info = report.info ?? {};
    console.log(
        `${file}: glTF validator ${report.validatorVersion}: ` +
            `${numErrors} errors, ${numWarnings} warnings, ${numInfos} infos, ${numHints} hints` +
            ` (${info.totalVertexCount ?? '?'} vertices, ${info.totalTriangleCount ?? '?'} triangles,` +
            ` ${info.animationCount ?? 0} animations, ${info.materialCount ?? 0} materials)`,
    );
    for (let severity = 0; severity < SEVERITY.length; severity++) {
        const issues = messages.filter((m) => m.severity === severity);
        for (const m of issues.slice(0, SHOWN_PER_SEVERITY)) {
            console.log(`  ${SEVERITY[severity]} ${m.code} at ${m.pointer ?? m.offset ?? '-'}: ${m.message}`);
        }
        if (issues.length > SHOWN_PER_SEVERITY) {
            console.log(`  ... and ${issues.length - SHOWN_PER_SEVERITY} more of severity ${SEVERITY[severity]}`);
        }
    }
    if (numErrors > 0) failed = true;
}
process.exit(failed ? 1 : 0);
